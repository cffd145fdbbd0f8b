#!/usr/bin/env bash
# Issue 6: dense-rig / 0.05 m grid timing and an Nsight Compute profile of the hottest kernel (the batched
# M-SOG score kernel: 16 dense rigs on the 0.05 m grid) and an A/B of its variants on the GPU host.   source /tmp/gpu-env.sh && bash bench/gpu_profile.sh
set -uo pipefail
out=${OUT:-bench/results}
mkdir -p "$out"
if [ -d .whl ]; then python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl 2>/dev/null; fi
timeout 300 python3 bench/gpu_score_variants.py --voxel 0.05 --pop 16 2>&1 | grep -v "CUDA warning" | tail -40
timeout 200 python3 bench/gpu_dense.py 2>&1 | grep -v "CUDA warning" | tail -5
NCU=$(command -v ncu || ls /usr/local/cuda*/bin/ncu /opt/nvidia/nsight-compute/*/ncu 2>/dev/null | head -1)
echo "ncu: ${NCU:-not found}"
if [ -n "${NCU:-}" ]; then
  cat > /tmp/prof_score.py <<'PY'
import numpy as np, place3d_kernels as p3k
scene = p3k.scene.town(seed=0)
d = p3k.DEFAULT_GRID
psog = p3k.scene_psog(scene, grid=p3k.Grid(d.lower, d.upper, 0.05), backend="warp:cuda:0")   # the dense-rig goal
lidar = p3k.LidarModel.uniform(64, (-25, 15), 2048, max_range=100.0)
pop = np.repeat(p3k.Placement.load("pyramid").poses[None], 16, axis=0)
for _ in range(3):
    p3k.msog_batch(psog, lidar, pop, backend="warp:cuda:0")
PY
  timeout 150 "$NCU" --kernel-name regex:score_kernel --launch-skip 1 --launch-count 1 \
    --section SpeedOfLight --section MemoryWorkloadAnalysis --section Occupancy --section WarpStateStats \
    --section LaunchStats python3 /tmp/prof_score.py > "$out/ncu-score-kernel.txt" 2>&1
  grep -E "Duration|Throughput|Achieved Occupancy|Registers|Stall|L1/TEX Hit|L2 Hit|DRAM" "$out/ncu-score-kernel.txt" | head -40
fi
