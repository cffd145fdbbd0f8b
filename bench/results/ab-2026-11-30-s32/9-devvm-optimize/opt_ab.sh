#!/usr/bin/env bash
# warm default `place3d optimize --max-evals 2000` on the dev VM, old (4cc9510) against new, alternated, 3 runs each,
# one shared P-SOG cache filled first; each run's result.json best score compared
set -u
C=/tmp/s32/optcache; rm -rf $C; mkdir -p $C /tmp/s32/optab
cd /tmp
PLACE3D_CACHE=$C PYTHONPATH=/work/main python3 -m place3d_app optimize --max-evals 2000 --quiet --output /tmp/s32/optab/fill > /dev/null 2>&1
for r in 1 2 3; do
  if [ $r = 2 ]; then order="new old"; else order="old new"; fi
  for t in $order; do
    if [ $t = old ]; then pp=/tmp/s32/old; else pp=/work/main; fi
    rm -rf /tmp/s32/optab/$t-$r
    s=$(date +%s.%N)
    PLACE3D_CACHE=$C PYTHONPATH=$pp python3 -m place3d_app optimize --max-evals 2000 --quiet --output /tmp/s32/optab/$t-$r > /tmp/s32/optab/$t-$r.log 2>&1
    e=$(date +%s.%N)
    d=$(python3 -c "
import json,hashlib
r=json.load(open('/tmp/s32/optab/$t-$r/result.json'))
def clean(x):
    if isinstance(x, dict): return {k: clean(v) for k, v in x.items() if not any(w in k for w in ('time', 'machine', 'second', 'profile', 'path', 'output', 'version'))}
    if isinstance(x, list): return [clean(v) for v in x]
    return x
print(hashlib.sha256(json.dumps(clean(r), sort_keys=True).encode()).hexdigest()[:12])" 2>/dev/null)
    echo "$t $r $(python3 -c "print(round($e-$s,2))") digest $d"
  done
done
