#!/usr/bin/env bash
# A headless Chromium screenshot of the viser page after a Replica run (docs/viser_replica.png).
# Chromium comes from Debian's packages (apt-get install -y chromium); its software WebGL
# (SwiftShader) draws the splats. The run keeps serving after its last frame
# (viewer.keep_serving=true) until the screenshot is taken, then gets SIGTERM (a background job
# of a script ignores SIGINT).
#   bash benchmarks/viser_screenshot.sh [OUT.png] [FRAMES]
set -euo pipefail
OUT=${1:-docs/viser_replica.png}
FRAMES=${2:-20}
PORT=${PORT:-8097}
REPO=$(cd "$(dirname "$0")/.." && pwd)
DATA=${SLAMKIT_DATA:-$REPO/../shared/data}
RUN=$(mktemp -d)
cd "$REPO"
OMP_NUM_THREADS=1 .venv/bin/slamkit dataset=replica dataset.path="$DATA/replica_room0_first20" \
  dataset.max_frames="$FRAMES" mapper=gaussian_splatting iterations_per_frame=5 final_iterations=100 \
  mapper.save_images=0 viewer=viser viewer.port="$PORT" viewer.keep_serving=true viewer.render_every=5 \
  output.progress=false hydra.run.dir="$RUN" > "$RUN/stdout.txt" 2>&1 &
PID=$!
trap 'kill -TERM $PID 2>/dev/null || true' EXIT
until grep -qs "Ctrl-C (or SIGTERM) to stop" "$RUN/stdout.txt"; do
  kill -0 $PID 2>/dev/null || { cat "$RUN/stdout.txt"; exit 1; }
  sleep 2
done
URL=$(grep -o "live map is at http://[0-9.:]*" "$RUN/stdout.txt" | head -1 | awk '{print $NF}')
chromium --headless=new --no-sandbox --use-angle=swiftshader --enable-unsafe-swiftshader \
  --window-size=1600,900 --hide-scrollbars --virtual-time-budget=20000 \
  --screenshot="$REPO/$OUT" "$URL/" 2>/dev/null
kill -TERM $PID
wait $PID || true
grep "slamkit:" "$RUN/stdout.txt" || true
cat "$RUN/viser.json"
echo "wrote $OUT"
