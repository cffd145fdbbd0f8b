import subprocess, sys, time
code = r'''
import os, sys, time
n = int(sys.argv[1])
if n >= 0:
    import warp as wp
    wp.config.quiet = True
    wp.init()
    a = [wp.zeros(n, dtype=wp.uint8, device="cuda:0") for _ in range(4)] if n else []
    wp.synchronize()
else:
    import numpy
sys.stdout.write("T %r\n" % time.time()); sys.stdout.flush()
os._exit(0)
'''
for rep in range(3):
    for n in [-1, 0, 1 << 28, 1 << 30]:
        p = subprocess.Popen([sys.executable, '-c', code, str(n)], stdout=subprocess.PIPE)
        lines = p.stdout.read().decode().splitlines(); p.wait()
        out = [l for l in lines if l.startswith('T ')][0][2:]; t1 = time.time()
        print(f"alloc {n:>11d} B x4: os._exit to process end {1000*(t1 - float(out)):.1f} ms", flush=True)
