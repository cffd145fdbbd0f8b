#!/bin/bash
# warm reproduce --routes 8 (every P-SOG in the cache), old vs new, alternated
cd /tmp
for r in 1 2 3; do
  for t in /tmp/old /tmp/new2; do
    s=$(date +%s.%N)
    PLACE3D_CACHE=/tmp/pc PYTHONPATH=$t python3 -m place3d_app reproduce --routes 8 --quiet --output /tmp/warm-out-$r > /tmp/warm-$r.txt 2>&1
    e=$(date +%s.%N)
    echo "$t run $r wall $(echo "$e - $s" | bc) $(grep -o '[0-9.]* s (pool [0-9.]* s, jackknife [0-9.]* s)' /tmp/warm-$r.txt) $(python3 -c "import json,hashlib;d=json.load(open('/tmp/warm-out-$r/reproduce.json'));print(hashlib.sha256(json.dumps([d['tasks'],d['convergence']],sort_keys=True).encode()).hexdigest()[:12])")"
  done
done
