#!/usr/bin/env bash
# The HTTP tour (docs/http.md): upload a recording shipped with kincal, calibrate it, read the
# verdict, fetch the report, rank configurations, export for the controller and check the
# calibration against poses — with curl and jq against a running `kincal serve`. From the
# repository root:
#
#   kincal serve &              # prints: kincal ... listening on http://127.0.0.1:8000 ...
#   bash docs/http_tour.sh      # KINCAL_URL=http://host:port for another address
#
# Keyless on loopback (the default); with keys: KINCAL_API_KEY=$(kincal keys create --tenant me).
# Files go to out/http_tour/ (OUT=... to change). tests/service/api/test_http_tour.py runs this
# script as written against a fresh `kincal serve`.
set -euo pipefail

URL=${KINCAL_URL:-http://127.0.0.1:8000}
API=$URL/api/v1
OUT=${OUT:-out/http_tour}
RECORDING=data/real/philnad_fr3_eye_in_hand/fr3_poses.csv   # a Franka FR3, 114 poses
mkdir -p "$OUT"
call() { curl -sS --fail-with-body -H "X-API-Key: ${KINCAL_API_KEY:-}" "$@"; }

# 0. Wait until the service is ready (its workers started).
for _ in $(seq 180); do curl -sf "$URL/readyz" >/dev/null && break; sleep 1; done
call "$URL/readyz" | jq -c .

# 1. Upload the recording (the same pre-flight checks as the CLI: a file in millimetres or
#    degrees is a 422 naming the fix). The answer holds the dataset's id.
DATASET=$(call -F robot=panda -F "file=@$RECORDING" "$API/datasets" | jq -r .id)
echo "dataset $DATASET"

# 2. Calibrate it with the default options: 202 Accepted, then poll the job.
CALIBRATION=$(call -H 'content-type: application/json' -d "{\"dataset_id\": \"$DATASET\"}" \
  "$API/calibrations" | jq -r .id)
echo "calibration $CALIBRATION"
while :; do
  STATUS=$(call "$API/calibrations/$CALIBRATION")
  STATE=$(jq -r .status.state <<<"$STATUS")
  echo "  $STATE $(jq -r '.status.stage // ""' <<<"$STATUS") $(jq -r .status.fraction <<<"$STATUS")"
  case $STATE in succeeded) break ;; failed | cancelled) exit 1 ;; esac
  sleep 2
done

# 3. The verdict (ok, warning or failed, each reason with its fix) and the report.
jq -c '{verdict: .verdict.status, reasons: [.verdict.reasons[].code]}' <<<"$STATUS"
call "$API/calibrations/$CALIBRATION/report" >"$OUT/report.html"

# 4. Rank configurations by their predicted uncertainty (Eq. 22-23), best first: here the
#    recording's first five rows, 7 joint angles each (q1..q7, radians).
CONFIGURATIONS=$(sed -n 2,6p "$RECORDING" | cut -d, -f2-8 |
  jq -R -s -c 'split("\n") | map(select(length > 0) | split(",") | map(tonumber))')
call -H 'content-type: application/json' "$API/rankings" \
  -d "{\"calibration_id\": \"$CALIBRATION\", \"joint_positions_rad\": $CONFIGURATIONS}" |
  jq -c '[.ranking[] | {index, score}]' | tee "$OUT/ranking.json"

# 5. The calibrated URDF for the controller (refused with 409 when the verdict failed).
call "$API/calibrations/$CALIBRATION/urdf" >"$OUT/fr3_calibrated.urdf"

# 6. Is it still calibrated? Check it against new poses (kincal check, under a second, kept
#    with its time: GET .../checks lists them). Ten rows of the recording stand in for poses
#    recorded later here; rows the calibration used show the call, not the check's power.
sed -n 1,11p "$RECORDING" >"$OUT/check_poses.csv"
CHECK_SET=$(call -F robot=panda -F "file=@$OUT/check_poses.csv" "$API/datasets" | jq -r .id)
call -H 'content-type: application/json' -d "{\"dataset_id\": \"$CHECK_SET\"}" \
  "$API/calibrations/$CALIBRATION/checks" | jq -c '{verdict, statistic, threshold, located}'

echo "wrote: $OUT/report.html $OUT/ranking.json $OUT/fr3_calibrated.urdf"
