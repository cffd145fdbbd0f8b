[ -f /tmp/gpu-env.sh ] || exit 3
source /tmp/gpu-env.sh
pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl 2>&1 | tail -1
rm -rf /tmp/probe && cp -r .old/probe /tmp/probe
nvidia-smi --query-gpu=name --format=csv,noheader
python3 bench/cold_profile.py --bytecode --runs 4 --tree . --tree /tmp/probe:PROBE_CHILD_FASTEXIT=1 --tree /tmp/probe:PROBE_SWITCH=0.001 --tree .:PLACE3D_JACKKNIFE_PREFETCH=0 --label=-ab-H100-2026-11-26-s11a --out $OUT 2>&1 | grep -v "^#" | tail -12
