#!/usr/bin/env bash
# The GPU checks in one call, for a session lent a GPU machine (docs/notebook/benchmarks-2026-11.md, "First
# measurements on a GPU"): the CUDA tests, the rasterizer bench, then stage 3 (deblur + eval, --profile) on each run
# folder given, optionally against another code root (an A/B in one call, baseline first).
#
#   bash bench/gpu_check.sh [RUN ...]
#
# RUN: a run folder holding pose/ and refine/ from a CPU run (stage 1 needs open3d, which GPU machines
# may lack); a copy is worked on, so RUN is not changed. Environment: ARCH (cuda), PY (python3), OUT
# (where logs.tgz goes, /tmp/gpu_check), BASELINE (a code root holding taichi_gs/ to time first),
# REMAP ("old=new": rewrite the sequence path in each copy's run.json), CONFIG (a --config TOML for
# deblur), T_TESTS / T_STAGE (per-step time limits, s). Taichi must be importable by PY.
#
# Carrying taichi to a machine without it (2026-11-27: 64 MiB may travel, taichi 1.7.4's cp312 wheel is 56 MB):
# unzip the wheel and the dill and plyfile wheels into one folder, drop taichi/_lib/c_api (the C API library,
# unused from Python) and taichi-1.7.4.data, zip the rest (35 MB), then on the machine run
# `python3 -m zipfile -e site.zip /tmp/site` and put /tmp/site on PYTHONPATH.
set -u
ARCH=${ARCH:-cuda}; PY=${PY:-python3}; OUT=${OUT:-/tmp/gpu_check}; LOGS=$(mktemp -d)
ROOT=$(cd "$(dirname "$0")/.." && pwd)
export PYTHONUNBUFFERED=1
mkdir -p "$OUT"
step() {  # name limit command...: run with a time limit, keep its log, print its tail
  local name=$1 limit=$2; shift 2; echo "=== $name (limit $limit s) $(date +%T)"; local t0=$SECONDS
  timeout "$limit" "$@" > "$LOGS/$name.log" 2>&1; local rc=$?; echo "--- $name rc=$rc $((SECONDS - t0)) s"
  grep -v "^SKIPPED\|SyntaxWarning\|Save a field" "$LOGS/$name.log" | tail -n 6
  tar czf "$OUT/logs.tgz" -C "$LOGS" .
}
runs=(); for run in "$@"; do runs+=("$(cd "$run" && pwd)") || exit 2; done  # absolute, before the cd
[ -n "${CONFIG:-}" ] && CONFIG=$(realpath "$CONFIG")
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader 2>&1 | tee "$LOGS/machine.txt"
cd "$ROOT"
step tests_render "${T_TESTS:-120}" env PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}" \
  $PY -m pytest -q -p no:cacheprovider -m cuda tests/test_render.py
step tests_gpu "${T_TESTS:-120}" env TAICHI_GS_ARCH="$ARCH" PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}" \
  $PY -m pytest -q -p no:cacheprovider -m gpu tests/test_gpu_backend.py
step raster 60 env PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}" $PY bench/raster.py --arch "$ARCH" --quick
arms="new"; [ -n "${BASELINE:-}" ] && arms="old new"
for run in "${runs[@]}"; do
  for arm in $arms; do
    code=$ROOT; [ "$arm" = old ] && code=$BASELINE
    name=$(basename "$run")_$arm; copy=$LOGS/run_$name
    rm -rf "$copy"; mkdir -p "$copy"; cp -r "$run"/pose "$run"/refine "$run"/run.json "$copy"/
    [ -n "${REMAP:-}" ] && sed -i "s#\"${REMAP%%=*}#\"${REMAP#*=}#" "$copy/run.json"
    cli="env PYTHONPATH=$code${PYTHONPATH:+:$PYTHONPATH} $PY -m taichi_gs.cli --arch $ARCH"
    # from another directory: python -m puts the working directory ahead of PYTHONPATH, so in ROOT the
    # baseline arm would import ROOT's code
    step "$name" "${T_STAGE:-300}" bash -c "cd $LOGS && time $cli deblur $copy --profile ${CONFIG:+--config $CONFIG} \
      && $cli eval $copy --json > $LOGS/$name.eval.json"
    cp "$copy/profile.md" "$LOGS/$name.profile.md" 2>/dev/null
    rm -rf "$copy"; tar czf "$OUT/logs.tgz" -C "$LOGS" .
  done
done
echo "=== end $(date +%T): $OUT/logs.tgz"
