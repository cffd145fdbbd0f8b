#!/usr/bin/env bash
# One batch on the lent GPU host (see ../shared/gpu/README.md): cross-backend tests for the GPU backends,
# then the kernel benchmarks and the peers. Run after the .gpu parts are staged:
#   source /tmp/gpu-env.sh && bash bench/gpu_run.sh
# Results go to $OUT (the device tool brings them back) or bench/results/: gpu-tests-<label>-<date>.txt (the
# GPU, the backends found, the tests' tail), kernels-<label>-<date>.json, peers-<label>-<date>.json and
# summary.json (the committed one with this run merged in). GPU_LABEL names the machine (default gpu-<GPU name>,
# the label of the GPU's run in summary.json).
set -uo pipefail
out=${OUT:-bench/results}
mkdir -p "$out"
# start from the committed summary so that the merge keeps the other machines' runs
[ "$out" != bench/results ] && cp bench/results/summary.json "$out/summary.json"
if [ -d .whl ]; then python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl; fi
label=${GPU_LABEL:-gpu-$(nvidia-smi --query-gpu=name --format=csv,noheader | head -1 | tr ' ' '-')}
log="$out/gpu-tests-$label-$(date -u +%F).txt"
device=$(nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | head -1)
{ echo "$device"; python3 -c "import place3d_kernels as p; print(p.available_backends())"; } | tee "$log"
gpus=$(python3 -c "import place3d_kernels as p; print(','.join(b for b in p.available_backends() if b.startswith('warp:cuda') or (b.startswith('opencl:') and b != 'opencl:pocl')))")
PLACE3D_TEST_BACKENDS="$gpus" timeout 420 python3 -m pytest -q -p no:cacheprovider -x tests/test_traversal.py \
  tests/test_raycast.py tests/test_msog.py tests/test_sog.py tests/test_pipeline.py tests/test_opencl_backend.py \
  tests/stress 2>&1 | tail -25 | tee -a "$log"
timeout 300 python3 bench/run_bench.py --label "$label" --device "$device" --backends ${gpus//,/ } --out "$out" 2>&1 | tail -15
# peers on the same host (Open3D / Embree / Mitsuba where importable; the pure-Python traversal baseline
# always), merged into the run of the same label in $out/summary.json
timeout 240 python3 bench/peers.py --label "$label" --device "$device" --out "$out" 2>&1 | tail -25
