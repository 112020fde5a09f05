#!/usr/bin/env bash
# The GPU check (docs/gpu.md): on a machine with a GPU and no registry access, install gsplat and
# slamkit's missing dependencies from the wheels carried in .whl/, install slamkit without
# dependencies, build gsplat's CUDA extension once (kept in .cache/torch_extensions for a later
# run), run the `cuda` tests, then time tracking, one mapping step by phase and real-time GS-ICP
# runs (benchmarks/gpu_bench.py), writing gpu_check.json and gpu_check.md as it goes.
#
#   bash benchmarks/gpu_check.sh --dry-run    # every step it would take, printed; runs nothing
#   GPU_CHECK_OUT=$OUT bash benchmarks/gpu_check.sh
#
# Environment: GPU_CHECK_OUT (results folder, default benchmarks/results/gpu_check),
# SLAMKIT_DATA (the sequences, default .gpudata/ if present, else ../shared/data),
# GPU_CHECK_WHEELS (default .whl/), GPU_CHECK_BUDGET_S (whole run, default 540 s: each step's
# limit is cut to what is left), GPU_CHECK_ONLY (comma-separated step names: run only these, e.g.
# a rerun on the still-warm machine), PYTHON (default python3).
# Every step prints a line when it starts and one when it ends, so a cut-off run says how far it got.
set -u -o pipefail

DRY=0
case "${1:-}" in
  --dry-run) DRY=1 ;;
  "") ;;
  *) echo "usage: bash benchmarks/gpu_check.sh [--dry-run]" >&2; exit 2 ;;
esac

REPO=$(cd "$(dirname "$0")/.." && pwd)
cd "$REPO"
PY=${PYTHON:-python3}
OUT_DIR=${GPU_CHECK_OUT:-$REPO/benchmarks/results/gpu_check}
WHEELS=${GPU_CHECK_WHEELS:-$REPO/.whl}
if [ -n "${SLAMKIT_DATA:-}" ]; then DATA=$SLAMKIT_DATA
elif [ -d "$REPO/.gpudata" ]; then DATA=$REPO/.gpudata
else DATA=$(cd "$REPO/.." && pwd)/shared/data; fi
BUDGET=${GPU_CHECK_BUDGET_S:-540}
SITE=$REPO/.cache/gpu_check/site

export SLAMKIT_DATA=$DATA
export TORCH_EXTENSIONS_DIR=$REPO/.cache/torch_extensions   # gsplat's build, kept for a later run
export SLAMKIT_CACHE=$REPO/.cache/slamkit                   # the compiled CPU kernels, likewise
export MAX_JOBS=${MAX_JOBS:-$(nproc)}                       # parallel nvcc jobs of the gsplat build
export PYTHONUNBUFFERED=1
export PYTHONPATH=$SITE${PYTHONPATH:+:$PYTHONPATH}
export PATH="$(dirname "$(command -v "$PY" || echo /usr/bin/python3)"):$PATH"   # ninja beside python

START=$(date +%s)
NO_GSPLAT=""
FAILED=0

wanted() {  # is step $1 to run (GPU_CHECK_ONLY unset, or naming it)?
  [ -z "${GPU_CHECK_ONLY:-}" ] || [[ ",$GPU_CHECK_ONLY," == *",$1,"* ]]
}

stage_cap() {  # seconds at most for a timing stage
  case $1 in tracking) echo 60 ;; phases) echo 100 ;; realtime) echo 200 ;; esac
}

say() { echo "[gpu_check +$(( $(date +%s) - START ))s] $*"; }

note() {  # STEP STATUS SECONDS DETAIL: recorded in gpu_check.json
  [ "$DRY" = 1 ] && return 0
  "$PY" -B benchmarks/gpu_bench.py note "$@" --out "$OUT_DIR" || true
}

# step NAME CAP_S COMMAND...: run COMMAND under `timeout`, limited to CAP_S and to what is left of
# the budget; records its status and time. Returns the command's status.
step() {
  local name=$1 cap=$2; shift 2
  if ! wanted "$name"; then
    [ "$DRY" = 1 ] && echo "STEP $name: left out (not in GPU_CHECK_ONLY)" || say "SKIP $name (not in GPU_CHECK_ONLY)"
    return 0
  fi
  local left=$(( BUDGET - ($(date +%s) - START) ))
  local limit=$(( cap < left ? cap : left ))
  if [ "$DRY" = 1 ]; then
    echo "STEP $name (limit ${cap} s): $*"
    return 0
  fi
  if [ "$limit" -lt 10 ]; then
    say "SKIP $name: ${left} s left of the ${BUDGET} s budget"
    note "$name" skipped 0 "no time left"
    return 124
  fi
  say "START $name (limit ${limit} s): $*"
  local t0 rc
  t0=$(date +%s)
  timeout -k 10 "$limit" "$@"
  rc=$?
  local secs=$(( $(date +%s) - t0 ))
  local status=ok
  [ "$rc" = 0 ] || status="failed (status $rc)"
  [ "$rc" = 124 ] || [ "$rc" = 137 ] && status="timed out after ${limit} s"
  say "END $name: $status in ${secs} s"
  note "$name" "$status" "$secs" "$*"
  [ "$rc" = 0 ] || FAILED=1
  return "$rc"
}

if [ "$DRY" = 1 ]; then
  echo "gpu_check --dry-run: the steps a real run takes (nothing is run, installed, built or timed)"
  echo "repository: $REPO"
  echo "python: $PY"
  echo "output folder: $OUT_DIR (gpu_check.log, gpu_check.json, gpu_check.md, gsplat_build.log, pytest_cuda.log)"
  echo "wheels: $WHEELS"
  echo "data: $DATA"
  echo "budget: $BUDGET s in all"
  echo "TORCH_EXTENSIONS_DIR=$TORCH_EXTENSIONS_DIR SLAMKIT_CACHE=$SLAMKIT_CACHE PYTHONPATH=$PYTHONPATH"
fi

run_steps() {
  step machine 30 bash -c "nvidia-smi -L; nvcc --version | tail -n 2; \"$PY\" -c 'import torch; print(\"torch\", torch.__version__, \"cuda\", torch.version.cuda, \"available\", torch.cuda.is_available())'"

  step install-wheels 90 "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target "$SITE" $(ls "$WHEELS"/*.whl 2>/dev/null || echo "$WHEELS/*.whl")

  step install-slamkit 90 "$PY" -m pip install -q --no-index --no-deps --no-build-isolation -e "$REPO"

  step import-slamkit 60 "$PY" -c "from slamkit.registry.discovery import default_registry; \
  print('slamkit plugins:', {r: sorted(p) for r, p in default_registry().plugins.items()})"

  if [ "$DRY" = 1 ]; then
    step build-gsplat 330 "$PY" benchmarks/build_gsplat.py "> $OUT_DIR/gsplat_build.log"
  else
    step build-gsplat 330 bash -c "\"$PY\" benchmarks/build_gsplat.py > \"$OUT_DIR/gsplat_build.log\" 2>&1; \
  rc=\$?; if [ \$rc = 0 ]; then grep '^build_gsplat' \"$OUT_DIR/gsplat_build.log\"; else tail -n 20 \"$OUT_DIR/gsplat_build.log\"; fi; exit \$rc" \
      || NO_GSPLAT=1
  fi

  if [ -n "$NO_GSPLAT" ]; then
    say "gsplat's extension is not ready: the gsplat tests and timings are left out"
    step cuda-tests 150 bash -c "set -o pipefail; \"$PY\" -m pytest -m cuda -q -k 'not gsplat' tests/e2e/test_cuda.py 2>&1 | tee \"$OUT_DIR/pytest_cuda.log\""
  else
    step cuda-tests 150 bash -c "set -o pipefail; \"$PY\" -m pytest -m cuda -q tests/e2e/test_cuda.py 2>&1 | tee \"$OUT_DIR/pytest_cuda.log\""
  fi

  BENCH=("$PY" benchmarks/gpu_bench.py --out "$OUT_DIR" --data "$DATA")
  [ -n "$NO_GSPLAT" ] && BENCH+=(--no-gsplat)
  for stage in tracking phases realtime; do
    step "time-$stage" "$(stage_cap "$stage")" "${BENCH[@]}" "$stage"
    if [ "$DRY" = 1 ] && wanted "time-$stage"; then
      "$PY" -B benchmarks/gpu_bench.py plan "$stage" --data "$DATA" ${NO_GSPLAT:+--no-gsplat} || return 1
    fi
  done

  if [ "$DRY" = 1 ]; then
    echo "then: the table in $OUT_DIR/gpu_check.md and the JSON in $OUT_DIR/gpu_check.json"
    return 0
  fi
  say "done in $(( $(date +%s) - START )) s; results: $OUT_DIR/gpu_check.md"
  cat "$OUT_DIR/gpu_check.md" 2>/dev/null
  return "$FAILED"
}

if [ "$DRY" = 1 ]; then
  run_steps
  exit $?
fi
mkdir -p "$OUT_DIR" "$SITE"
say "gpu_check: repository $REPO, output $OUT_DIR, data $DATA, budget $BUDGET s" | tee -a "$OUT_DIR/gpu_check.log"
run_steps 2>&1 | tee -a "$OUT_DIR/gpu_check.log"
exit "${PIPESTATUS[0]}"
