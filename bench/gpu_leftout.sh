#!/usr/bin/env bash
# The routes' jackknife with every record's left-out rows made on the device in one batch
# (left_out.device_fields, warp/left_out_kernels.py), on the lent GPU host:
#   1. the bit-identity tests on every Warp device there (CUDA included): device rows against the host's,
#      NumPy's order of addition, patched grids against uploaded ones;
#   2. `place3d --profile reproduce --routes 8 --backend warp:cuda:0` RUNS times (default 2) on one warm P-SOG
#      cache (the first run builds it and compiles the new module; the later runs are the warm figures), the
#      profile table of each kept.
# Run after the .gpu parts are staged (../shared/gpu/README.md):
#   source /tmp/gpu-env.sh && bash bench/gpu_leftout.sh
# Writes $OUT/leftout-gpu-<date>.json (or bench/results/): the tests' summary line and, per run, the wall
# seconds and the profile's jackknife rows.
set -uo pipefail
out=${OUT:-bench/results}
mkdir -p "$out"
if [ -d .whl ]; then python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl; fi
runs=${RUNS:-2}
cache=$(mktemp -d)
tmp=$(mktemp -d)
python3 -m pytest -q tests/test_left_out.py -k "device or numpys_order or patched or every_normalisation" \
    > "$tmp/tests.txt" 2>&1
for i in $(seq 1 "$runs"); do
  s=$(date +%s.%N)
  PLACE3D_CACHE=$cache python3 -m place3d_app --profile reproduce --routes 8 --backend warp:cuda:0 \
      --output "$tmp/reproduce-$i" --quiet > "$tmp/run-$i.out" 2> "$tmp/run-$i.err"
  echo "$s $(date +%s.%N)" > "$tmp/run-$i.time"
done
python3 - "$tmp" "$runs" "$out/leftout-gpu-$(date -u +%F).json" <<'PY'
import json, subprocess, sys
tmp, runs, dest = sys.argv[1], int(sys.argv[2]), sys.argv[3]
def gpu():
    try:
        return subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version", "--format=csv,noheader"],
                              capture_output=True, text=True).stdout.strip()
    except OSError:
        return None
res = {"gpu": gpu(), "tests": open(f"{tmp}/tests.txt").read().strip().splitlines()[-1:], "runs": []}
for i in range(1, runs + 1):
    a, b = (float(x) for x in open(f"{tmp}/run-{i}.time").read().split())
    err = open(f"{tmp}/run-{i}.err").read().splitlines()
    rows = [l for l in err if l.lstrip().startswith(("jackknife", "P-SOG", "total", "(not in"))]
    res["runs"].append({"wall_s": round(b - a, 2), "profile": rows})
json.dump(res, open(dest, "w"), indent=2)
print(json.dumps(res, indent=2))
PY
