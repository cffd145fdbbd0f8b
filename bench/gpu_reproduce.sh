#!/usr/bin/env bash
# issue 36, goal 1 on the lent GPU host: `place3d reproduce --routes 8 --backend warp:cuda:0` (four towns,
# P-SOGs pooled from scratch, the eight placements, intervals, convergence) timed three times with a warm
# Warp kernel cache (bench/bench_pool.py: an empty P-SOG cache per run, one untimed small run first).
# Run after the .gpu parts are staged (../shared/gpu/README.md):
#   source /tmp/gpu-env.sh && bash bench/gpu_reproduce.sh
# Environment: ROUTES (default 8), RUNS (default 3), VOXEL (the command's --voxel-size; default its own), BASELINE=1 to alternate `--executor local` (the drives
# one after the other, as before issue 36) with the default (auto: one worker process per core), OLD=DIR to
# alternate another checkout (its place3d_kernels and place3d_app) with this one, PROFILE=1 to add one
# `place3d --profile reproduce` run (empty P-SOG cache, kernel cache warmed first) whose table lands in
# $out/reproduce-profile-<date>.log. A `run`
# command on the host may take 10 minutes: where the runs do not fit, call the script once per run with
# RUNS=1 (bench_pool.py rewrites its file after every run, so a run cut short keeps the runs before it).
# Writes $OUT/reproduce-pool-gpu-<machine>-<date>.json (or bench/results/) and a log beside it.
set -uo pipefail
out=${OUT:-bench/results}
mkdir -p "$out"
if [ -d .whl ]; then python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl; fi
routes=${ROUTES:-8}
runs=${RUNS:-3}
log="$out/reproduce-pool-gpu-$(date -u +%F).log"
{ nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | head -1; nproc;
  python3 -c "import place3d_kernels as p; print(p.available_backends())"; } | tee "$log"
args=(--routes "$routes" --runs "$runs" --backend warp:cuda:0 --out "$out" --label gpu)
[ -n "${VOXEL:-}" ] && args+=(--voxel-size "$VOXEL")
[ -n "${OLD:-}" ] && args+=(--tree "$OLD" --tree .)
# BASELINE=1: the local executor (the drives one after the other, as before issue 36) alternates with the
# default on the same machine
[ "${BASELINE:-0}" = 1 ] && args+=(--executors local auto)
python3 bench/bench_pool.py "${args[@]}" 2>&1 | tee -a "$log"
if [ "${PROFILE:-0}" = 1 ]; then
  prof="$out/reproduce-profile-$(date -u +%F).log"
  c=$(mktemp -d); w=$(mktemp -d)
  WARP_CACHE_PATH=$w PLACE3D_CACHE=$c python3 -m place3d_app reproduce --towns town --routes 2 --frames 2 \
    --no-convergence --backend warp:cuda:0 --quiet --output "$c/warm" >/dev/null 2>&1
  rm -rf "$c"; c=$(mktemp -d)
  WARP_CACHE_PATH=$w PLACE3D_CACHE=$c python3 -m place3d_app --profile reproduce --routes "$routes" \
    --backend warp:cuda:0 --quiet --output "$c/out" >"$prof" 2>&1
  rm -rf "$c" "$w"; tail -30 "$prof"
fi
