"""Scale benchmark (issue 7): streamed calibration of 10³…10⁶ poses and a fleet of robots.

For each N, a simulated Kinova Jaco2 recording (every joint compliant, random perturbations of
every joint frame, sensor noise, 1 % gross outliers) is written to Parquet (row groups of
``chunk_rows``), then each backend runs the streamed pipeline end to end —
read → deterministic (first fit, 2σ rule, refit, "before" fit) → covariance (moment matching,
Eq. 13–14) — in a fresh process, so that peak memory is that run's: wall time per stage, peak
resident memory of the driver and of the largest worker (VmHWM), CPU seconds of all its
processes (on a machine shared with other work, CPU time / cores is what an idle machine would
take), the number of passes over the data, and what else ran meanwhile: the 1-minute load
average before and after (the run itself adds up to its worker count) and the CPU seconds the
rest of the machine used during the run (machine-wide busy time minus the run's own; Linux).
``--idle F`` waits before each run until the machine's CPUs are at most a fraction F busy.
The scaling exponents are log-log slopes of time and memory against N, over N ≥ 10⁴ and over
the top decade; fixed costs (worker start, warm start) flatten them, so the table also fits CPU
time = a + b·N (linear with an intercept).

Stages: "read" = planning, starting the workers and preparing every chunk (the first warm
start runs beside it on the driver); "deterministic" = the refit's and "before" fit's warm
starts and the streamed fits; "covariance" = the solve and the sandwich pass (the statistics
come with the refit's last pass).

Then a fleet of robots (one Parquet file each) is calibrated by ``kincal fleet``'s code on each
backend.

Prints a table, writes ``scale.json`` in ``--out`` and the log-log plot to ``--plot``; with
``--write-results`` also ``docs/results/scale.{json,md}`` (wall time per backend, peak memory
without the chunk cache, passes, per N), ``scale_stages`` (every run's stages, CPU and memory),
``scale_cpu`` (the CPU-time fit and scaling exponents) and ``scale_fleet``, the tables
docs/large-recordings.md and docs/scale.md include. ``--from-results`` runs nothing and
re-writes those tables (not the fleet's) and the plot from ``docs/results/scale.json``.

Usage: ``python -m benchmarks.scale [--sizes 1e3,1e4,1e5,1e6] [--backends inprocess,processes,
dask] [--uncached inprocess] [--fleet-robots 100] [--fleet-poses 2000] [--cache-mb 512]
[--idle 0.1] [--out out/scale] [--plot docs/scale.png] [--write-results]``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

import solver  # noqa: F401  (BLAS defaults)
from benchmarks.results import Row, count_text, markdown_table, read_results, write_results
from schemas.calibration import CalibrationOptions
from schemas.dataset import PoseDataset, dataset_to_frame, write_dataset
from schemas.robots import load_robot
from service.app import calibrate as pipeline
from service.app import simulate as scenarios
from service.render import result_json
from solver import lie
from solver.executors import make_executor, peak_rss_bytes
from solver.gravity import StaticGravityModel, static_gravity_loads
from solver.kinematics import forward_kinematics
from solver.model import KinematicChain, sample_configurations
from solver.simulate import SimulationSpec, look_at, simulate_recording, true_parameters

ROBOT = "kinova"
SIZES = (1_000, 10_000, 100_000, 1_000_000)
BACKENDS = ("inprocess", "processes", "dask")
STAGES = ("read", "deterministic", "covariance")
MiB = 1024 * 1024


def spec(n: int, seed: int, chain: KinematicChain) -> SimulationSpec:
    """The simulated robot: compliant joints 2 and 3, random perturbations, noise, outliers."""
    return SimulationSpec(
        n_samples=n,
        seed=seed,
        compliance_rad_per_nm={
            chain.compliance_axes[1].name: 5e-4,
            chain.compliance_axes[2].name: 8e-4,
        },
        perturbation_sigma=np.full((chain.n_joints, 6), 5e-5),
        noise_sigma=np.array([5e-5] * 3 + [1e-4] * 3),
        measurement_frame=look_at(np.array([0.8, -0.5, 0.45]), np.array([0.0, 0.0, 0.3])),
        outlier_fraction=0.01,
    )


def write_recording(path: Path, chain: KinematicChain, n: int, *, chunk_rows: int) -> None:
    """Simulate ``n`` poses of one robot, ``chunk_rows`` at a time, into Parquet row groups
    (the robot is drawn once; every chunk draws its own configurations and noise)."""
    simulation = spec(n, 1, chain)
    rng = np.random.default_rng(1)
    params, _ = true_parameters(chain, simulation, rng)
    gravity = StaticGravityModel.from_chain(chain)
    assert simulation.perturbation_sigma is not None
    writer = None
    try:
        for start in range(0, n, chunk_rows):
            m = min(chunk_rows, n - start)
            q = sample_configurations(chain, m, rng)
            loads = static_gravity_loads(gravity, q)
            xi = rng.normal(size=(m, chain.n_joints, 6)) * simulation.perturbation_sigma
            pose = forward_kinematics(chain, params, q, loads, perturbations=xi)
            noise = rng.normal(size=(m, 6)) * simulation.noise_sigma
            pose = pose @ lie.se3_exp(noise)
            gross = rng.random(m) < simulation.outlier_fraction
            kick = rng.normal(size=(int(gross.sum()), 6)) * np.r_[[5e-3] * 3, [0.17] * 3]
            pose[gross] = pose[gross] @ lie.se3_exp(kick)
            dataset = PoseDataset(
                joint_names=chain.joint_names,
                joint_positions=q,
                position_m=pose[:, :3, 3],
                quaternion_xyzw=lie.matrix_to_quaternion_xyzw(pose[:, :3, :3]),
                sample_id=np.arange(start + 1, start + m + 1),
            )
            table = pa.Table.from_pandas(dataset_to_frame(dataset), preserve_index=False)
            if writer is None:
                writer = pq.ParquetWriter(path.with_suffix(".tmp"), table.schema)
            writer.write_table(table, row_group_size=chunk_rows)
    finally:
        if writer is not None:
            writer.close()
    path.with_suffix(".tmp").replace(path)


def machine_busy_s() -> float | None:
    """CPU seconds every process of the machine has used since boot (Linux ``/proc/stat``),
    None where that is not available."""
    try:
        with open("/proc/stat", encoding="ascii") as stat:
            fields = [int(x) for x in stat.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    user, nice, system, _idle, _iowait, irq, softirq, steal = (fields + [0] * 8)[:8]
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def children_cpu_s() -> float:
    """CPU seconds of this process's finished (waited-for) children and their descendants."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def wait_until_idle(max_busy: float, timeout_s: float, window_s: float = 2.0) -> float:
    """Wait until the machine's CPUs are at most ``max_busy`` (fraction) busy over
    ``window_s``, or ``timeout_s`` passed; returns the last busy fraction seen."""
    deadline = time.monotonic() + timeout_s
    cores = os.cpu_count() or 1
    while True:
        before = machine_busy_s()
        if before is None:
            return 0.0
        time.sleep(window_s)
        after = machine_busy_s() or before
        busy = (after - before) / (window_s * cores)
        if busy <= max_busy or time.monotonic() > deadline:
            return busy


@dataclass
class Run:
    """One streamed calibration: N, backend, seconds per stage, peak memory (MiB)."""

    n: int
    backend: str
    workers: int
    stage_s: dict[str, float]
    total_s: float
    cpu_s: float
    driver_mib: float
    worker_mib: float
    passes: int
    rms_after_mm: float
    compliance_rad_per_nm: list[float] = field(default_factory=list)
    cache_mb: float = 512.0
    load_average: tuple[float, float] = (0.0, 0.0)
    other_cpu_s: float = 0.0
    unreaped_cpu_s: float = 0.0
    """CPU of workers that ``RUSAGE_CHILDREN`` never sees: the ``processes`` backend's
    workers are children of the forkserver, which nobody waits for."""

    @property
    def label(self) -> str:
        """Backend, marked when prepared chunks were not cached (memory independent of N)."""
        return self.backend if self.cache_mb else f"{self.backend}-nocache"


def run_one(
    path: Path, n: int, backend: str, *, chunk_rows: int, cache_mb: float, workers: int
) -> Run:
    """Streamed calibration of ``path`` on ``backend`` (call in a fresh process)."""
    robot = load_robot(ROBOT)
    options = CalibrationOptions(covariance_estimator="moment", heldout=False)
    stream = pipeline.StreamOptions(chunk_rows=chunk_rows, cache_mb=cache_mb)
    load_before = os.getloadavg()[0]
    started = time.perf_counter()
    executor = make_executor(backend, n_workers=workers)  # type: ignore[arg-type]
    ready = time.perf_counter()
    try:
        setup = pipeline.check_calibration(robot, options)
        run = pipeline.calibrate_source(path, setup, executor=executor, stream=stream)
        result, timings = run.result, run.timings
        total = time.perf_counter() - started
        worker_peaks = executor.run_on_workers(peak_rss_bytes)
        worker_cpu = executor.run_on_workers(time.process_time)
    finally:
        executor.close()
    cpu_s = time.process_time() + (sum(worker_cpu) if backend != "inprocess" else 0.0)
    unreaped_cpu_s = sum(worker_cpu) if backend == "processes" else 0.0
    stage = {
        "start": ready - started,
        "read": timings.get("open", 0.0) + timings.get("read", 0.0),
        "deterministic": timings.get("warm_start", 0.0) + timings.get("deterministic", 0.0),
        "covariance": timings.get("covariance", 0.0),
    }
    return Run(
        n,
        backend,
        executor.n_workers if backend == "inprocess" else workers,
        stage,
        total,
        cpu_s,
        peak_rss_bytes() / MiB,
        max(worker_peaks) / MiB,
        int(timings.get("passes", 0)),
        result.fit.after.train.translation_rms_mm,
        [c.value_rad_per_nm for c in result.compliance],
        cache_mb,
        (load_before, os.getloadavg()[0]),
        unreaped_cpu_s=unreaped_cpu_s,
    )


def run_isolated(
    path: Path, n: int, backend: str, *, chunk_rows: int, cache_mb: float, workers: int
) -> Run:
    """:func:`run_one` in a new interpreter (peak memory of this run alone)."""
    code = (
        "import json, sys; from pathlib import Path; from dataclasses import asdict; "
        "from benchmarks.scale import run_one; "
        f"r = run_one(Path({str(path)!r}), {n}, {backend!r}, chunk_rows={chunk_rows}, "
        f"cache_mb={cache_mb}, workers={workers}); print('RESULT' + json.dumps(asdict(r)))"
    )
    busy, own = machine_busy_s(), children_cpu_s()
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=False,
        cwd=Path(__file__).resolve().parents[1],
    )
    lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT")]
    if done.returncode or not lines:
        raise RuntimeError(f"{backend} at N={n} failed:\n{done.stderr[-3000:]}")
    values = json.loads(lines[-1][len("RESULT") :])
    values["load_average"] = tuple(values["load_average"])
    after = machine_busy_s()
    if busy is not None and after is not None:
        own_cpu_s = children_cpu_s() - own + values["unreaped_cpu_s"]
        values["other_cpu_s"] = max(0.0, (after - busy) - own_cpu_s)
    return Run(**values)


def slope(x: Sequence[float], y: Sequence[float]) -> float:
    """Least-squares slope of log y against log x."""
    return float(np.polyfit(np.log(np.asarray(x)), np.log(np.asarray(y)), 1)[0])


@dataclass
class FleetRun:
    backend: str
    n_robots: int
    n_poses: int
    wall_s: float
    robots_per_s: float
    flagged: list[str]
    other_cpu_s: float = 0.0


def write_fleet(folder: Path, chain: KinematicChain, n_robots: int, n_poses: int) -> None:
    """One Parquet file per robot; robot 7 (if any) has a worn joint 3 (2.5× compliance)."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(5)
    for r in range(n_robots):
        path = folder / f"SN{r:04d}.parquet"
        if path.exists():
            continue
        simulation = spec(n_poses, 1000 + r, chain)
        compliance = {
            k: v * (1 + 0.03 * rng.normal()) for k, v in simulation.compliance_rad_per_nm.items()
        }
        if r == 7:
            compliance[chain.compliance_axes[2].name] *= 2.5
        simulation = SimulationSpec(**{**simulation.__dict__, "compliance_rad_per_nm": compliance})
        recording = simulate_recording(chain, simulation)
        write_dataset(scenarios.recording_dataset(recording, chain, rotation=True), path)


def run_fleet(folder: Path, backend: str, workers: int) -> FleetRun:
    from service.app.fleet import calibrate_fleet, fleet_datasets

    robot = load_robot(ROBOT)
    options = CalibrationOptions(covariance_estimator="moment", heldout=False)
    datasets = fleet_datasets(folder)
    busy, own = machine_busy_s(), children_cpu_s() + time.process_time()
    started = time.perf_counter()
    with make_executor(backend, n_workers=workers) as executor:  # type: ignore[arg-type]
        report, _ = calibrate_fleet(datasets, robot, options, executor)
        wall = time.perf_counter() - started
        worker_cpu = executor.run_on_workers(time.process_time)
    after = machine_busy_s()
    unreaped_cpu_s = sum(worker_cpu) if backend == "processes" else 0.0  # see Run
    other = 0.0
    if busy is not None and after is not None:
        own_cpu_s = children_cpu_s() + time.process_time() - own + unreaped_cpu_s
        other = max(0.0, (after - busy) - own_cpu_s)
    flagged = sorted({f"{o.serial}:{o.parameter}" for o in report.outliers})
    n_poses = report.robots[0].n_samples if report.robots else 0
    return FleetRun(backend, len(datasets), n_poses, wall, len(datasets) / wall, flagged, other)


def table(runs: list[Run], fleets: list[FleetRun]) -> str:
    header = (
        f"{'backend':<18} {'N':>9} {'read s':>8} {'determ. s':>10} {'cov. s':>8} "
        f"{'total s':>8} {'CPU s':>7} {'driver MiB':>11} {'worker MiB':>11} {'passes':>7} "
        f"{'load':>9} {'other CPU s':>11}"
    )
    lines = [header]
    for r in runs:
        lines.append(
            f"{r.label:<18} {r.n:>9} {r.stage_s['read']:>8.2f} "
            f"{r.stage_s['deterministic']:>10.2f} {r.stage_s['covariance']:>8.2f} "
            f"{r.total_s:>8.2f} {r.cpu_s:>7.1f} {r.driver_mib:>11.0f} {r.worker_mib:>11.0f} "
            f"{r.passes:>7} {r.load_average[0]:>4.1f}-{r.load_average[1]:<4.1f} "
            f"{r.other_cpu_s:>11.1f}"
        )
    for smallest in (10_000, 100_000):
        lines += ["", f"scaling exponents (log-log slopes over N >= {smallest:.0e})"]
        for backend in dict.fromkeys(r.label for r in runs):
            mine = [r for r in runs if r.label == backend and r.n >= smallest]
            if len(mine) >= 2:
                n = [r.n for r in mine]
                memory = [max(r.driver_mib, r.worker_mib) for r in mine]
                stages = ", ".join(
                    f"{s} {slope(n, [max(r.stage_s[s], 1e-3) for r in mine]):.2f}" for s in STAGES
                )
                lines.append(
                    f"{backend:<18} wall {slope(n, [r.total_s for r in mine]):.2f} "
                    f"({stages}), CPU {slope(n, [r.cpu_s for r in mine]):.2f}, "
                    f"peak memory {slope(n, memory):.2f}"
                )
    lines += ["", "CPU time = a + b·N (least squares over N >= 1e4)"]
    for backend in dict.fromkeys(r.label for r in runs):
        mine = [r for r in runs if r.label == backend and r.n >= 10_000]
        if len(mine) >= 2:
            b, a = np.polyfit([r.n for r in mine], [r.cpu_s for r in mine], 1)
            lines.append(
                f"{backend:<18} a = {a:.1f} s, b = {b * 1e6:.1f} µs per pose "
                f"({b * 1e6:.1f} CPU-s per 10⁶ poses)"
            )
    if fleets:
        lines += [
            "",
            f"{'fleet':<10} {'robots':>7} {'poses':>6} {'wall s':>8} {'robots/s':>9} "
            f"{'other CPU s':>11}  flagged",
        ]
        lines += [
            f"{f.backend:<10} {f.n_robots:>7} {f.n_poses:>6} {f.wall_s:>8.1f} "
            f"{f.robots_per_s:>9.2f} {f.other_cpu_s:>11.1f}  {', '.join(f.flagged) or '-'}"
            for f in fleets
        ]
    return "\n".join(lines)


BACKEND_TITLES = {"inprocess": "in-process", "processes": "processes", "dask": "Dask (local)"}
"""Column titles of the backends in the results table."""


def render(rows: list[Row]) -> str:
    """The table of ``docs/results/scale.md`` from the runs (``asdict(Run)``): per N, the wall
    seconds of each cached backend (to 0.01 s; the fastest at the largest N in bold), the peak
    resident memory of the largest process without the chunk cache (MiB), the passes over the
    data, and the most CPU seconds the rest of the machine used during one of the N's runs
    (to 0.1 s; the ``processes`` backend's fork server counts ~1.5 s here)."""
    cached = [r for r in rows if r["cache_mb"]]
    backends = list(dict.fromkeys(r["backend"] for r in cached))
    workers = {r["backend"]: r["workers"] for r in cached}
    largest = max(r["n"] for r in rows)
    fastest = min((r for r in cached if r["n"] == largest), key=lambda r: r["total_s"])
    header = [
        f"{workers[b]} processes s" if b == "processes" else f"{BACKEND_TITLES.get(b, b)} s"
        for b in backends
    ]
    uncached = list(dict.fromkeys(r["backend"] for r in rows if not r["cache_mb"]))
    header += [f"peak MiB, {BACKEND_TITLES.get(b, b)} without chunk cache" for b in uncached]
    table = []
    for n in sorted({r["n"] for r in rows}):
        mine = [r for r in rows if r["n"] == n]
        cells: list[object] = [count_text(n)]
        for backend in backends:
            (run,) = [r for r in mine if r["backend"] == backend and r["cache_mb"]]
            text = f"{run['total_s']:.2f}"
            cells.append(f"**{text}**" if run is fastest else text)
        for backend in uncached:
            (run,) = [r for r in mine if r["backend"] == backend and not r["cache_mb"]]
            cells.append(f"{max(run['driver_mib'], run['worker_mib']):.0f}")
        cells.append(" / ".join(str(p) for p in sorted({r["passes"] for r in mine})))
        cells.append(f"{max(r['other_cpu_s'] for r in mine):.1f}")
        table.append(cells)
    return markdown_table(["poses", *header, "passes", "other CPU s, at most"], table)


def stage_rows(runs: Sequence[Run]) -> list[Row]:
    """Per run (backend, cached or not, and N): seconds per stage and in all, CPU seconds of
    all its processes, peak resident memory of its largest process, passes over the data and
    the CPU seconds the rest of the machine used meanwhile."""
    return [
        {
            "backend": r.label,
            "n": r.n,
            **{f"{stage}_s": r.stage_s[stage] for stage in STAGES},
            "total_s": r.total_s,
            "cpu_s": r.cpu_s,
            "peak_mib": max(r.driver_mib, r.worker_mib),
            "passes": r.passes,
            "other_cpu_s": r.other_cpu_s,
        }
        for r in runs
    ]


def render_stages(rows: list[Row]) -> str:
    """The table of ``docs/results/scale_stages.md``: per backend and N the seconds per stage
    and in all (to 0.01 s), CPU seconds and the other work's (to 0.1 s), peak MiB, passes."""
    return markdown_table(
        (
            "backend", "poses", "read s", "deterministic s", "covariance s", "total s",
            "CPU s", "peak MiB", "passes", "other CPU s",
        ),
        [
            (
                r["backend"], count_text(r["n"]), f"{r['read_s']:.2f}",
                f"{r['deterministic_s']:.2f}", f"{r['covariance_s']:.2f}", f"{r['total_s']:.2f}",
                f"{r['cpu_s']:.1f}", f"{r['peak_mib']:.0f}", r["passes"],
                f"{r['other_cpu_s']:.1f}",
            )
            for r in rows
        ],
    )  # fmt: skip


FIT_FROM = 10_000
"""The smallest N of the CPU-time fit and the scaling exponents."""


def cpu_rows(runs: Sequence[Run]) -> list[Row]:
    """Per backend (cached or not), over N ≥ :data:`FIT_FROM`: CPU time = a + b·N (least
    squares), and the log-log slopes of wall time and peak memory against N."""
    rows = []
    for backend in dict.fromkeys(r.label for r in runs):
        mine = [r for r in runs if r.label == backend and r.n >= FIT_FROM]
        if len(mine) < 2:
            continue
        n = [r.n for r in mine]
        b, a = np.polyfit(n, [r.cpu_s for r in mine], 1)
        rows.append(
            {
                "backend": backend,
                "sizes": n,
                "cpu_fixed_s": float(a),
                "cpu_per_pose_us": float(b * 1e6),
                "wall_exponent": slope(n, [r.total_s for r in mine]),
                "memory_exponent": slope(n, [max(r.driver_mib, r.worker_mib) for r in mine]),
            }
        )
    return rows


def render_cpu(rows: list[Row]) -> str:
    """The table of ``docs/results/scale_cpu.md``: per backend the fixed CPU seconds a (to
    0.1 s) and the CPU µs per pose b of CPU time = a + b·N, and the log-log slopes of wall
    time and peak memory (to 0.01), over the sizes fitted."""
    return markdown_table(
        ("backend", "sizes", "a: fixed CPU s", "b: CPU µs per pose", "wall exponent",
         "memory exponent"),
        [
            (
                r["backend"], "–".join(count_text(n) for n in (r["sizes"][0], r["sizes"][-1])),
                f"{r['cpu_fixed_s']:.1f}", f"{r['cpu_per_pose_us']:.1f}",
                f"{r['wall_exponent']:.2f}", f"{r['memory_exponent']:.2f}",
            )
            for r in rows
        ],
    )  # fmt: skip


def write_run_results(runs: Sequence[Run], command: str) -> tuple[Path, ...]:
    """``docs/results/scale{,_stages,_cpu}.{json,md}`` of ``runs``, ``command`` recorded."""
    return (
        *write_results("scale", command, [asdict(r) for r in runs], render),
        *write_results("scale_stages", command, stage_rows(runs), render_stages),
        *write_results("scale_cpu", command, cpu_rows(runs), render_cpu),
    )


def recorded_runs() -> tuple[str, list[Run]]:
    """The command and runs of ``docs/results/scale.json``."""
    command, rows = read_results("scale")
    runs = []
    for row in rows:
        runs.append(Run(**{**row, "load_average": tuple(row["load_average"])}))
    return command, runs


WORN = "SN0007:compliance."
"""The worn robot's flag (:func:`write_fleet`: robot 7, joint 3's compliance)."""


def render_fleet(rows: list[Row]) -> str:
    """The table of ``docs/results/scale_fleet.md`` from the fleet runs (``asdict(FleetRun)``):
    wall seconds (to 0.1 s), robots per second, whether the worn joint is flagged and how
    many other parameters are."""
    return markdown_table(
        ("backend", "robots × poses", "wall s", "robots/s", "worn joint flagged", "other flags"),
        [
            (
                BACKEND_TITLES.get(r["backend"], r["backend"]),
                f"{r['n_robots']} × {r['n_poses']}",
                f"{r['wall_s']:.1f}",
                f"{r['robots_per_s']:.2f}",
                ", ".join(f.split(":")[1] for f in r["flagged"] if f.startswith(WORN)) or "**no**",
                sum(not f.startswith(WORN) for f in r["flagged"]),
            )
            for r in rows
        ],
    )


def plot(runs: list[Run], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    for i, backend in enumerate(dict.fromkeys(r.label for r in runs)):
        mine = sorted((r for r in runs if r.label == backend), key=lambda r: r.n)
        n = [r.n for r in mine]
        color = f"C{i}"
        left.loglog(n, [r.total_s for r in mine], "o-", color=color, label=f"{backend} wall")
        left.loglog(n, [r.cpu_s for r in mine], "x--", color=color, label=f"{backend} CPU")
        right.semilogx(
            n, [max(r.driver_mib, r.worker_mib) for r in mine], "o-", color=color, label=backend
        )
    left.plot([1e6], [10.0], "k*", markersize=12, label="target: 10 s at 10⁶")
    right.axhline(2048, color="k", linestyle=":", label="target 2 GiB")
    right.set_ylim(0, 2200)
    if runs:
        sizes = np.array(sorted({r.n for r in runs}), dtype=float)
        fastest = min((r for r in runs if r.n == sizes[-1]), key=lambda r: r.total_s)
        left.loglog(sizes, fastest.total_s * sizes / sizes[-1], "k:", label="linear")
    left.set(xlabel="poses N", ylabel="time (s)", title="read → deterministic → covariance")
    right.set(xlabel="poses N", ylabel="peak resident memory (MiB)", title="largest process")
    for ax in (left, right):
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(
    sizes: Sequence[int] = SIZES,
    backends: Sequence[str] = BACKENDS,
    *,
    out: Path = Path("out/scale"),
    plot_path: Path | None = Path("docs/scale.png"),
    fleet_robots: int = 100,
    fleet_poses: int = 2000,
    chunk_rows: int = 65_536,
    cache_mb: float = 512.0,
    workers: int | None = None,
    uncached: Sequence[str] = (),
    idle: float | None = None,
    idle_timeout_s: float = 600.0,
    echo=print,  # type: ignore[no-untyped-def]
    write: str | None = None,
) -> tuple[str, list[Run], list[FleetRun]]:
    """Run the benchmark; returns the table and the measurements. ``idle``: before each run,
    wait (up to ``idle_timeout_s``) until the machine is at most that fraction busy.
    ``write``: the command line to record in ``docs/results/scale{,_fleet}.json`` (written
    with their tables when given)."""

    def settle() -> None:
        if idle is not None:
            busy = wait_until_idle(idle, idle_timeout_s)
            if busy > idle:
                echo(f"machine still {100 * busy:.0f} % busy after {idle_timeout_s:.0f} s")

    workers = workers or os.cpu_count() or 1
    out.mkdir(parents=True, exist_ok=True)
    chain = result_json.chain_for(load_robot(ROBOT), CalibrationOptions())
    runs: list[Run] = []
    for n in sizes:
        path = out / f"kinova_{n}.parquet"
        if not path.exists():
            clock = time.perf_counter()
            write_recording(path, chain, n, chunk_rows=chunk_rows)
            echo(f"simulated N={n} in {time.perf_counter() - clock:.1f} s -> {path}")
        plan = [(b, cache_mb) for b in backends] + [(b, 0.0) for b in uncached]
        for backend, cache in plan:
            settle()
            run = run_isolated(
                path, n, backend, chunk_rows=chunk_rows, cache_mb=cache, workers=workers
            )
            echo(
                f"{run.label:<18} N={n:>8}: {run.total_s:7.2f} s, "
                f"{max(run.driver_mib, run.worker_mib):6.0f} MiB"
            )
            runs.append(run)
    fleets: list[FleetRun] = []
    if fleet_robots:
        folder = out / f"fleet_{fleet_robots}x{fleet_poses}"
        write_fleet(folder, chain, fleet_robots, fleet_poses)
        for backend in backends:
            settle()
            fleets.append(run_fleet(folder, backend, workers))
            echo(f"fleet on {backend}: {fleets[-1].wall_s:.1f} s")
    summary = table(runs, fleets)
    (out / "scale.json").write_text(
        json.dumps({"runs": [asdict(r) for r in runs], "fleets": [asdict(f) for f in fleets]})
    )
    if plot_path is not None and runs:
        plot(runs, plot_path)
    if write is not None:
        written: tuple[Path, ...] = write_run_results(runs, write)
        if fleets:
            written += write_results(
                "scale_fleet", write, [asdict(f) for f in fleets], render_fleet
            )
        for path in written:
            echo(f"wrote {path}")
    return summary, runs, fleets


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default=",".join(str(s) for s in SIZES))
    parser.add_argument("--backends", default=",".join(BACKENDS))
    parser.add_argument("--out", type=Path, default=Path("out/scale"))
    parser.add_argument("--plot", type=Path, default=Path("docs/scale.png"))
    parser.add_argument("--fleet-robots", type=int, default=100)
    parser.add_argument("--fleet-poses", type=int, default=2000)
    parser.add_argument("--chunk-rows", type=int, default=65_536)
    parser.add_argument("--cache-mb", type=float, default=512.0)
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument(
        "--uncached", default="", help="Backends to run again without the chunk cache."
    )
    parser.add_argument(
        "--idle",
        type=float,
        default=None,
        help="Before each run wait until the CPUs are at most this fraction busy (e.g. 0.1).",
    )
    parser.add_argument(
        "--write-results",
        action="store_true",
        help="write docs/results/scale.{json,md} and scale_fleet.{json,md}",
    )
    parser.add_argument(
        "--from-results",
        action="store_true",
        help="run nothing: re-write docs/results/scale{,_stages,_cpu} and the plot (--plot) "
        "from the runs recorded in docs/results/scale.json",
    )
    args = parser.parse_args()
    if args.from_results:
        recorded, runs = recorded_runs()
        for path in write_run_results(runs, recorded):
            print(f"wrote {path}")
        if args.plot is not None:
            plot(runs, args.plot)
            print(f"wrote {args.plot}")
        sys.exit(0)
    report = main(
        [int(float(s)) for s in args.sizes.split(",")],
        args.backends.split(","),
        out=args.out,
        plot_path=args.plot,
        fleet_robots=args.fleet_robots,
        fleet_poses=args.fleet_poses,
        chunk_rows=args.chunk_rows,
        cache_mb=args.cache_mb,
        workers=args.workers,
        uncached=[b for b in args.uncached.split(",") if b],
        idle=args.idle,
        write=" ".join(["python -m benchmarks.scale", *sys.argv[1:]])
        if args.write_results
        else None,
    )[0]
    print(report)
