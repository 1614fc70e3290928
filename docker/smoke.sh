#!/usr/bin/env bash
# Smoke test of the container image without a Docker daemon:
#   1. debootstrap a minimal Debian (python3, python3-venv) and import it as the base image,
#   2. build docker/Dockerfile with buildah on that base (BASE_IMAGE build argument),
#   3. run `kincal serve` inside the image (buildah run --isolation chroot; it shares this
#      machine's network, so the server binds 127.0.0.1 only) and check /healthz, /readyz, and
#      that API keys are required.
# Needs root, buildah, debootstrap, curl and access to the Debian mirror and PyPI. Takes minutes
# and downloads about 0.5 GB, so it is not part of the test suite.
#   Usage: docker/smoke.sh            (SUITE=bookworm MIRROR=... PORT=18080 to override)
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

step() { printf '\n== %s (%s)\n' "$*" "$(date +%T)"; }

cleanup() {
    if [ -n "$SERVER_PID" ] && kill -0 "$SERVER_PID" 2>/dev/null; then
        kill -TERM "$SERVER_PID" 2>/dev/null || true
        wait "$SERVER_PID" 2>/dev/null || true
    fi
    if [ -n "$CTR" ]; then buildah rm "$CTR" >/dev/null 2>&1 || true; fi
    rm -rf "$WORK"
}
trap cleanup EXIT

for tool in buildah debootstrap curl; do
    command -v "$tool" >/dev/null || { echo "smoke.sh: $tool not found (apt-get install buildah debootstrap curl)" >&2; exit 2; }
done

if buildah inspect --type image "$BASE" >/dev/null 2>&1; then
    step "base image $BASE already present"
else
    step "debootstrap $SUITE (minbase + python3, python3-venv, ca-certificates)"
    debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates \
        "$SUITE" "$WORK/rootfs" "$MIRROR" >"$WORK/debootstrap.log" 2>&1 \
        || { tail -20 "$WORK/debootstrap.log"; exit 1; }
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
buildah build --isolation chroot --layers "${BUILD_MOUNTS[@]}" \
    --ignorefile docker/Dockerfile.dockerignore \
    --build-arg BASE_IMAGE="$BASE" \
    -f docker/Dockerfile -t "$IMAGE" . 2>&1 | grep -E '^(STEP|COMMIT|Successfully)|rror' || true
buildah inspect --type image "$IMAGE" >/dev/null
buildah images --format '{{.Name}}:{{.Tag}} {{.Size}}' "$IMAGE"
buildah inspect --type image --format 'user={{.OCIv1.Config.User}} cmd={{.OCIv1.Config.Cmd}}' "$IMAGE"

step "run kincal serve in the image on 127.0.0.1:$PORT"
CTR=$(buildah from "$IMAGE")
buildah run --isolation chroot \
    --env KINCAL_ALLOW_KEYLESS_LOCALHOST=false --env KINCAL_LOG_FORMAT=text \
    "$CTR" -- kincal serve --host 127.0.0.1 --port "$PORT" >"$WORK/server.log" 2>&1 &
SERVER_PID=$!
# Live first (/healthz), ready once the worker process is up (/readyz).
for probe in healthz readyz; do
    for _ in $(seq 1 120); do
        if curl -fsS "http://127.0.0.1:$PORT/$probe" >/dev/null 2>&1; then break; fi
        if ! kill -0 "$SERVER_PID" 2>/dev/null; then cat "$WORK/server.log"; exit 1; fi
        sleep 1
    done
done

step "checks"
echo "GET /healthz -> $(curl -fsS "http://127.0.0.1:$PORT/healthz")"
echo "GET /readyz  -> $(curl -fsS "http://127.0.0.1:$PORT/readyz")"
code=$(curl -s -o "$WORK/unauth.json" -w '%{http_code}' "http://127.0.0.1:$PORT/api/v1/datasets")
echo "GET /api/v1/datasets without key -> $code $(cat "$WORK/unauth.json")"
[ "$code" = 401 ]
echo "process user in the image: uid $(buildah run --isolation chroot "$CTR" -- id -u)"

step "stop (SIGTERM) and server log"
kill -TERM "$SERVER_PID"
wait "$SERVER_PID" || true
SERVER_PID=""
cat "$WORK/server.log"
echo
echo "smoke test passed"
