"""Entry point of the processes :mod:`service.jobs.supervisor` starts (not a user command).

``python -m service.api.child web --listen-fd N --wake-fd W --parent-pid P --run-dir D``
serves HTTP on the inherited socket; ``... runner --wake-fd R ...`` runs the jobs. Settings
come from the environment the supervisor passes on (its own, plus ``KINCAL_HOST``/``PORT`` and
``PROMETHEUS_MULTIPROC_DIR``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from service.jobs.lifeline import die_with_parent


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m service.api.child")
    parser.add_argument("role", choices=["web", "runner"])
    parser.add_argument("--parent-pid", type=int, required=True)
    parser.add_argument("--run-dir", type=Path, required=True)
    parser.add_argument("--index", type=int, default=0)
    parser.add_argument("--wake-fd", type=int, required=True)
    parser.add_argument("--listen-fd", type=int)
    args = parser.parse_args(argv)
    die_with_parent(args.parent_pid)  # first: before the imports, which take seconds

    from service.jobs import logs
    from service.settings import Settings

    settings = Settings()
    logs.process_name = "runner" if args.role == "runner" else f"web-{args.index}"
    logs.configure_logging(settings.log_level, settings.log_format)  # before the big imports
    from service.api import server

    if args.role == "runner":
        server.run_job_runner(settings, args.run_dir, args.wake_fd)
    else:
        if args.listen_fd is None:
            parser.error("web needs --listen-fd")
        server.serve_requests(settings, args.listen_fd, args.run_dir, args.wake_fd)


if __name__ == "__main__":
    main()
