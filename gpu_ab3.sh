[ -f /tmp/gpu-env.sh ] || exit 3
source /tmp/gpu-env.sh
pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl 2>&1 | grep -v WARNING | tail -1
rm -rf /tmp/base /tmp/plot && cp -r .old/base /tmp/base && cp -r .old/plot /tmp/plot
python3 -m pytest -q -x tests/test_left_out.py tests/test_coverage_panel.py tests/test_cold_simulate.py tests/test_scene_prefetch.py tests/test_warp_aot.py 2>&1 | tail -2
python3 bench/cold_profile.py --bytecode --runs 6 --tree /tmp/base --tree /tmp/plot --tree . --label=-ab-H100-2026-11-26-s11c --out $OUT 2>&1 | grep -v "^#" | tail -4
