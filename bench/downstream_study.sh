#!/usr/bin/env bash
# The downstream study of issue 35 on one GPU host: the paper's eight placements, trained on three CARLA
# towns and tested on other routes of them and on a held-out town; a BEV U-Net, 3 seeds per rig; mIoU with
# intervals, M-SOG (three normalisations), Kendall tau, the plot (docs/downstream.md); and the detection
# proxy from the same models: vehicle and pedestrian object recall per rig with intervals and tau
# ("objects" in results.json, the *_recall columns of table.csv, the plot's second row, the log).
#
#   bash bench/downstream_study.sh            # on the GPU host, from the repository root
#
# Stage the package's dependencies first as for bench/gpu_run.sh (warp-lang and the other wheels in
# .whl/, installed into /tmp/site here). The work folder (datasets, cells) is $WORK, outside $OUT, so a
# second call on the same warm machine resumes where a first one stopped (datasets and finished cells are
# skipped by their manifests). Results (7 files) go to $OUT/downstream-<date>/ when the device tool sets
# $OUT, else to bench/results/downstream-<date>/.
#
# Budget: sized for about 10 minutes of one H100 (see docs/downstream.md for the estimate and its
# parts); every size below can be overridden from the environment, e.g. STEPS=600 SEEDS=0-4.
# EXECUTOR=ray runs the dataset tasks on a local Ray cluster of $WORKERS CPUs (each task asks for
# $GPUS_PER_TASK of the GPU) instead of $WORKERS local processes; it needs Ray on the host.
set -uo pipefail
day=$(date -u +%Y-%m-%d)
out=${OUT:-bench/results}/downstream-$day
work=${WORK:-/tmp/place3d-downstream}
mkdir -p "$out" "$work"
if [ -d .whl ]; then python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl; fi
export PYTHONPATH="$PWD:/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
export PLACE3D_CACHE=${PLACE3D_CACHE:-$work/cache}

RIGS=${RIGS:-center,line,pyramid,square,trapezoid,line-roll,pyramid-roll,ours-seg}
TOWNS=${TOWNS:-Town01,Town03,Town04}
HELDOUT=${HELDOUT:-Town06}
TRAIN_ROUTES=${TRAIN_ROUTES:-0,1}
TEST_ROUTES=${TEST_ROUTES:-100}
FRAMES=${FRAMES:-40}
STEPS=${STEPS:-300}
SEEDS=${SEEDS:-0,1,2}
MODELS=${MODELS:-bev}
WORKERS=${WORKERS:-8}
EXECUTOR=${EXECUTOR:-}
GPUS_PER_TASK=${GPUS_PER_TASK:-0.125}
BACKEND=${BACKEND:-warp:cuda:0}
LIMIT=${LIMIT:-570}          # seconds; the device tool stops a command at 600

t0=$(date +%s)
{
  date -u +%FT%TZ
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
  python3 -c "import torch, place3d_kernels as p; print('torch', torch.__version__, 'cuda', torch.version.cuda); print(p.available_backends())"
  echo "cpus $(nproc)"
  echo "settings: rigs=$RIGS towns=$TOWNS heldout=$HELDOUT train_routes=$TRAIN_ROUTES test_routes=$TEST_ROUTES frames=$FRAMES steps=$STEPS seeds=$SEEDS models=$MODELS workers=$WORKERS executor=${EXECUTOR:-process} backend=$BACKEND"
} 2>&1 | tee "$out/machine.txt"

if [ "$EXECUTOR" = ray ]; then
  datasets=(--executor ray --num-cpus "$WORKERS" --gpus-per-task "$GPUS_PER_TASK")
else
  datasets=(--workers "$WORKERS")
fi
timeout "$LIMIT" python3 -m place3d_app.cli downstream --rigs "$RIGS" --towns "$TOWNS" \
  --heldout-towns "$HELDOUT" --train-routes "$TRAIN_ROUTES" --test-routes "$TEST_ROUTES" --frames "$FRAMES" \
  --steps "$STEPS" --seeds "$SEEDS" --models "$MODELS" "${datasets[@]}" --backend "$BACKEND" \
  --device cuda --output "$work/study" --quiet 2>&1 | tee "$out/log.txt"
rc=${PIPESTATUS[0]}
t1=$(date +%s)
echo "exit $rc; wall $((t1 - t0)) s for this call (machine start and transfers not included)" | tee "$out/time.txt"
if [ -f "$work/study/results.json" ]; then
  cp "$work/study/results.json" "$work/study/table.csv" "$work/study/msog_vs_miou.png" "$out/" 2>/dev/null
  tar -czf "$out/cells.tar.gz" -C "$work/study" cells 2>/dev/null
fi
[ "$rc" = 124 ] && echo "stopped at ${LIMIT} s: run the script again on the same warm machine to resume" | tee -a "$out/time.txt"
exit "$rc"
