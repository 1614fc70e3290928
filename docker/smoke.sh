#!/usr/bin/env bash
# Smoke test of the container image without a Docker daemon:
#   1. debootstrap a minimal Debian (python3, python3-venv) and import it as the base image,
#   2. build docker/Dockerfile with buildah on that base (BASE_IMAGE build argument),
#   3. run the image's own CMD (buildah run --isolation chroot; it shares this machine's network,
#      so KINCAL_HOST=127.0.0.1 keeps it on loopback) and check /healthz, /readyz, the image's
#      HEALTHCHECK command, that API keys are required, that the server is not root, a whole
#      upload -> calibration job -> result -> report round trip with the Python client inside
#      the image, and a graceful SIGTERM shutdown.
# Needs root, buildah, debootstrap, curl, ss and access to the Debian mirror and PyPI. Takes about
# ten minutes the first time and downloads about 0.5 GB, so it is not part of the test suite.
#   Usage: docker/smoke.sh            (SUITE=bookworm MIRROR=... PORT=18080 to override)
#   DATABASE_URL=postgresql+psycopg://user:pw@127.0.0.1:5432/db docker/smoke.sh runs the server
#   in the image on that (empty or kincal-migrated) PostgreSQL database instead of SQLite.
set -euo pipefail
cd "$(dirname "$0")/.."

SUITE=${SUITE:-bookworm}
MIRROR=${MIRROR:-http://deb.debian.org/debian}
PORT=${PORT:-18080}
BASE=localhost/kincal-debian-base:${SUITE}
IMAGE=localhost/kincal:smoke
WORK=$(mktemp -d /tmp/kincal-smoke.XXXXXX)
CTR=""
SERVER_PID=""
LISTENER=""

step() { printf '\n== %s (%s, %ss)\n' "$*" "$(date +%T)" "$SECONDS"; }

cleanup() {
    if [ -n "$SERVER_PID" ] && kill -0 "$SERVER_PID" 2>/dev/null; then
        # The server first (buildah run kills its child outright on SIGTERM), then buildah run.
        if [ -n "$LISTENER" ]; then kill -TERM "$LISTENER" 2>/dev/null || true; fi
        for _ in $(seq 1 30); do kill -0 "$SERVER_PID" 2>/dev/null || break; sleep 1; done
        kill -TERM "$SERVER_PID" 2>/dev/null || true
        wait "$SERVER_PID" 2>/dev/null || true
    fi
    if [ -n "$CTR" ]; then buildah rm "$CTR" >/dev/null 2>&1 || true; fi
    rm -rf "$WORK"
}
trap cleanup EXIT

fail() {
    echo "smoke.sh: $*" >&2
    if [ -s "$WORK/server.log" ]; then echo "--- server log:" >&2; cat "$WORK/server.log" >&2; fi
    exit 1
}

for tool in buildah debootstrap curl ss; do
    command -v "$tool" >/dev/null || fail "$tool not found (apt-get install buildah debootstrap curl iproute2)"
done

if buildah inspect --type image "$BASE" >/dev/null 2>&1; then
    step "base image $BASE already present"
else
    step "debootstrap $SUITE (minbase + python3, python3-venv, ca-certificates)"
    debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates \
        "$SUITE" "$WORK/rootfs" "$MIRROR" >"$WORK/debootstrap.log" 2>&1 \
        || { tail -20 "$WORK/debootstrap.log"; fail "debootstrap failed"; }
    rm -rf "$WORK/rootfs/var/cache/apt/archives/"*.deb "$WORK/rootfs/var/lib/apt/lists/"*
    step "import the root file system as $BASE"
    tar -C "$WORK/rootfs" --exclude='./dev/*' --exclude='./proc/*' --exclude='./sys/*' \
        -cf "$WORK/rootfs.tar" .
    base_ctr=$(buildah from scratch)
    buildah add "$base_ctr" "$WORK/rootfs.tar" / >/dev/null
    buildah config --cmd '["/bin/bash"]' --env LANG=C.UTF-8 "$base_ctr"
    buildah commit --rm "$base_ctr" "$BASE" >/dev/null
    rm -rf "$WORK/rootfs" "$WORK/rootfs.tar"
fi
buildah images --format '{{.Name}}:{{.Tag}} {{.Size}}' "$BASE"

step "build docker/Dockerfile on $BASE"
# Behind a TLS-intercepting proxy the RUN steps need this machine's CA bundle and pip settings;
# they are mounted for the build only and do not end up in the image.
BUILD_MOUNTS=()
if [ -f /etc/ssl/certs/ca-certificates.crt ]; then
    BUILD_MOUNTS+=(--volume /etc/ssl/certs/ca-certificates.crt:/etc/ssl/certs/ca-certificates.crt:ro)
fi
if [ -f /etc/pip.conf ]; then BUILD_MOUNTS+=(--volume /etc/pip.conf:/etc/pip.conf:ro); fi
# Docker image format: the OCI format has no HEALTHCHECK, and buildah would drop it.
# The full build log is kept in $WORK/build.log; its steps are echoed, and its tail on failure.
STEPS='^(\[[0-9]+/[0-9]+\] )?(STEP|COMMIT)|^Successfully tagged'
if ! buildah build --isolation chroot --layers --format docker "${BUILD_MOUNTS[@]}" \
    --ignorefile docker/Dockerfile.dockerignore \
    --build-arg BASE_IMAGE="$BASE" \
    -f docker/Dockerfile -t "$IMAGE" . >"$WORK/build.log" 2>&1; then
    grep -E "$STEPS" "$WORK/build.log" || true
    tail -40 "$WORK/build.log" >&2
    fail "build failed (last lines of the build log above)"
fi
grep -E "$STEPS" "$WORK/build.log"
if grep -E '^(WARN|level=warn)' "$WORK/build.log"; then echo "(build warnings above)"; fi
echo "image size: $(buildah images --format '{{.Name}}:{{.Tag}} {{.Size}}' "$IMAGE")"
buildah inspect --type image --format \
    'user={{.Docker.Config.User}} cmd={{.Docker.Config.Cmd}} healthcheck={{.Docker.Config.Healthcheck.Test}}' \
    "$IMAGE"
mapfile -t CMD < <(buildah inspect --type image --format '{{range .Docker.Config.Cmd}}{{println .}}{{end}}' "$IMAGE" | sed '/^$/d')
mapfile -t HEALTHCHECK < <(buildah inspect --type image --format '{{range .Docker.Config.Healthcheck.Test}}{{println .}}{{end}}' "$IMAGE" | sed '/^$/d')
[ "${#CMD[@]}" -gt 0 ] || fail "the image has no CMD"
[ "${HEALTHCHECK[0]:-}" = CMD ] || fail "the image has no exec-form HEALTHCHECK"

step "run the image's CMD (${CMD[*]}) on 127.0.0.1:$PORT"
# The container shares this machine's network: make sure nothing else answers on the port.
if curl -s -o /dev/null "http://127.0.0.1:$PORT/"; then
    fail "something already listens on 127.0.0.1:$PORT (set PORT=...)"
fi
CTR=$(buildah from "$IMAGE")
DB_ENV=()
if [ -n "${DATABASE_URL:-}" ]; then
    DB_ENV=(--env "KINCAL_DATABASE_URL=$DATABASE_URL")
    echo "database: $(sed -E 's#://([^:@/]*):[^@/]*@#://\1:***@#' <<<"$DATABASE_URL")"
else
    echo "database: SQLite in the image's data folder (default)"
fi
RUN_ENV=(--env KINCAL_HOST=127.0.0.1 --env "KINCAL_PORT=$PORT" --env KINCAL_LOG_FORMAT=text
         --env KINCAL_ALLOW_KEYLESS_LOCALHOST=false "${DB_ENV[@]}")
buildah run --isolation chroot "${RUN_ENV[@]}" "$CTR" -- "${CMD[@]}" >"$WORK/server.log" 2>&1 &
SERVER_PID=$!
# Live first (/healthz), ready once the worker process is up (/readyz).
for probe in healthz readyz; do
    for attempt in $(seq 1 120); do
        if curl -fsS "http://127.0.0.1:$PORT/$probe" >/dev/null 2>&1; then break; fi
        if ! kill -0 "$SERVER_PID" 2>/dev/null || [ "$attempt" = 120 ]; then
            fail "/$probe did not answer"
        fi
        sleep 1
    done
    echo "/$probe answered ${SECONDS}s into the smoke test"
done
# The process that listens on the port is the server from the image, and it is not root.
LISTENER=$(ss -Hltnp "sport = :$PORT" | grep -o 'pid=[0-9]*' | head -1 | cut -d= -f2)
[ -n "$LISTENER" ] || fail "no process found listening on port $PORT"

step "checks"
echo "GET /healthz -> $(curl -fsS "http://127.0.0.1:$PORT/healthz")"
echo "GET /readyz  -> $(curl -fsS "http://127.0.0.1:$PORT/readyz")"
buildah run --isolation chroot "${RUN_ENV[@]}" "$CTR" -- "${HEALTHCHECK[@]:1}" \
    || fail "the image's HEALTHCHECK command failed"
echo "HEALTHCHECK command of the image -> exit 0"
server_uid=$(awk '/^Uid:/ {print $2}' "/proc/$LISTENER/status")
echo "listening process: pid $LISTENER, uid $server_uid: $(tr '\0' ' ' <"/proc/$LISTENER/cmdline")"
[ "$server_uid" != 0 ] || fail "the server runs as root"
code=$(curl -s -o "$WORK/unauth.json" -w '%{http_code}' "http://127.0.0.1:$PORT/api/v1/datasets")
echo "GET /api/v1/datasets without key -> $code $(cat "$WORK/unauth.json")"
[ "$code" = 401 ] || fail "expected 401 without an API key"
# A key created in the image (same database as the server's) is accepted.
key=$(buildah run --isolation chroot "${DB_ENV[@]}" "$CTR" -- kincal keys create --tenant smoke 2>/dev/null)
code=$(curl -s -o "$WORK/auth.json" -w '%{http_code}' -H "X-API-Key: $key" \
    "http://127.0.0.1:$PORT/api/v1/datasets")
echo "GET /api/v1/datasets with a key from 'kincal keys create' -> $code $(cat "$WORK/auth.json")"
[ "$code" = 200 ] || fail "expected 200 with an API key"

step "round trip with the Python client inside the image"
E2E=$(cat <<'PY'
import subprocess, sys, time
from service.api.client import KincalClient

port, key = sys.argv[1], sys.argv[2]
path = "/tmp/smoke-recording.csv"
subprocess.run(["kincal", "simulate", "--robot", "ur10", "--n", "60", "--seed", "3", "-o", path],
               check=True)
with KincalClient(f"http://127.0.0.1:{port}", api_key=key) as client:
    dataset = client.upload_dataset(path, robot="ur10")
    print(f"uploaded dataset {dataset['id']}: {dataset['n_samples']} samples")
    started = time.monotonic()
    job = client.start_calibration(dataset["id"])
    status = client.wait(job["id"], timeout_s=600)
    print(f"calibration {job['id']}: {status['state']} in {time.monotonic() - started:.1f} s")
    result = client.result(job["id"])
    before, after = result.fit.before.train, result.fit.after.train
    print(f"translation RMS {before.translation_rms_mm:.2f} mm -> {after.translation_rms_mm:.3f} mm")
    assert after.translation_rms_mm < before.translation_rms_mm / 10, "calibration did not fit"
    report = client.report(job["id"])
    assert "<html" in report.lower(), "the report is not an HTML page"
    print(f"report: {len(report)} characters of HTML")
PY
)
buildah run --isolation chroot "$CTR" -- python3 -c "$E2E" "$PORT" "$key" \
    || fail "round trip inside the image failed"

step "SIGTERM to the server: graceful shutdown"
kill -TERM "$LISTENER"
for _ in $(seq 1 60); do kill -0 "$SERVER_PID" 2>/dev/null || break; sleep 1; done
if kill -0 "$SERVER_PID" 2>/dev/null; then fail "the server did not stop within 60 s of SIGTERM"; fi
wait "$SERVER_PID" && status=0 || status=$?
SERVER_PID=""
echo "server log (without the $(grep -c 'GET /api/v1/calibrations/[a-z0-9_]* 200' "$WORK/server.log") status polls):"
grep -v 'GET /api/v1/calibrations/[a-z0-9_]* 200' "$WORK/server.log"
# kincal serve exits 0 after a graceful shutdown (a signal status if it was killed); the log
# shows whether the shutdown was clean.
echo "buildah run exited with status $status"
for line in 'kincal service stopped' 'Application shutdown complete' 'Finished server process'; do
    grep -q "$line" "$WORK/server.log" || fail "no '$line' in the server log after SIGTERM"
done
if grep -E 'Traceback|ERROR' "$WORK/server.log"; then fail "errors in the server log"; fi
echo
echo "smoke test passed in ${SECONDS}s; image $(buildah images --format '{{.Name}}:{{.Tag}} {{.Size}}' "$IMAGE")"
