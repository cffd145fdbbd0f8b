"""Instructions on the common path of a voxel-walk kernel's inner loop, from its SASS (no GPU needed).

``gpu_dense_variants.py --registers`` uses this where ``cuobjdump`` is on PATH (the CUDA toolkit, or
``pip install nvidia-cuda-cuobjdump``): it disassembles the cubin that ptxas assembled and counts the
instructions of one loop iteration along the shortest path from the inner loop's head to its back edge
that avoids float64 arithmetic, atomics, calls and bit counts. For the study's kernels that path is the
common step: a float32 step that stays in the brick, with no flush and no float64 fallback. A static
count, not a timing: it says how many instructions a lane issues per such step, not how long it waits.

The inner loop is the second-largest backward branch: Warp wraps every CUDA kernel in a grid-stride
loop, which is the largest.
"""

from __future__ import annotations

import heapq
import re
import shutil
import subprocess

# instructions of the rare paths: float64 (the fallback and set-up), atomics and reductions (the flush),
# calls (slow division and float64 helpers), bit counts (the flush's weight loop)
RARE = re.compile(r"^(@!?U?P\w+ )?(D(ADD|MUL|FMA|SETP)|MUFU\.RCP64H|ATOM|RED|CALL|POPC)")
BOOKKEEPING = re.compile(r"^(BSSY|BSYNC|YIELD|NOP)")


def available() -> bool:
    return shutil.which("cuobjdump") is not None


def sass(cubin: str) -> list[tuple[int, str]]:
    """(address, instruction) pairs of the cubin's code."""
    out = subprocess.run(["cuobjdump", "-sass", cubin], capture_output=True, text=True, check=True).stdout
    ins = []
    for line in out.splitlines():
        m = re.match(r"\s+/\*([0-9a-f]{4,})\*/\s+(.*?);", line)
        if m:
            ins.append((int(m.group(1), 16), m.group(2).strip()))
    return ins


def _target(op: str) -> int | None:
    m = re.search(r"BRA (?:!?U?P\d, )?`?\(?(0x[0-9a-f]+)", op)
    return int(m.group(1), 16) if m else None


def common_step(ins: list[tuple[int, str]], listing: bool = False) -> dict:
    """The inner loop's common-path iteration: instruction count (without BSSY/BSYNC/YIELD/NOP, which
    mark reconvergence and scheduling), global loads and local-memory (spill) loads on it; ``listing``:
    also the path's instructions themselves (``common_step_listing``), to read what a step costs."""
    at = {a: i for i, (a, _) in enumerate(ins)}
    backs = sorted((at[a] - at[_target(op)], _target(op), a) for a, op in ins
                   if "BRA" in op and _target(op) is not None and _target(op) < a)
    if len(backs) < 2:
        raise ValueError("no inner loop found (fewer than two backward branches)")
    _, head, back = backs[-2]
    dist, prev, todo = {head: 0}, {}, [(0, head)]
    while todo:
        dcur, a = heapq.heappop(todo)
        if a == back:
            break
        if dcur > dist.get(a, 1 << 30):
            continue
        i = at[a]
        op = ins[i][1]
        if RARE.search(op):
            continue
        nxt = [_target(op)] if "BRA" in op and _target(op) is not None else []
        if not (op.startswith(("BRA", "EXIT", "RET"))) and i + 1 < len(ins):
            nxt.append(ins[i + 1][0])
        for b in nxt:
            if head <= b <= back and dcur + 1 < dist.get(b, 1 << 30):
                dist[b], prev[b] = dcur + 1, a
                heapq.heappush(todo, (dcur + 1, b))
    if back not in dist:
        raise ValueError("the inner loop has no path free of rare instructions")
    path = [back]
    while path[-1] != head:
        path.append(prev[path[-1]])
    ops = [ins[at[a]][1] for a in reversed(path)]
    out = {"common_step_instructions": sum(not BOOKKEEPING.match(o) for o in ops),
           "common_step_global_loads": sum("LDG" in o for o in ops),
           "common_step_spill_loads": sum("LDL" in o for o in ops)}
    if listing:
        out["common_step_listing"] = [o for o in ops if not BOOKKEEPING.match(o)]
    return out
