"""The first OpenCL build on a device says so before it compiles (issue 33, item 6, "Silent waits").

Before, the first command after the OpenCL extra was installed compiled PoCL's kernels for about 90 s
without a word. Now ``build_program`` logs one INFO line (which the command prints unless --quiet) when
the program was never built for this device before, and none once it was.
"""

from __future__ import annotations

import logging
import uuid

import pytest

rt = pytest.importorskip("place3d_kernels.backends.opencl._runtime")

SOURCE = "__kernel void note_probe(__global int *a) { a[get_global_id(0)] = 2; }"


@pytest.fixture
def ctx():
    import pyopencl as cl

    table = rt.platform_table()
    if not table:
        pytest.skip("no usable OpenCL platform")
    _, devs = next(iter(table.values()))
    return cl.Context(devs[:1])


def test_a_first_build_is_announced_once(ctx, monkeypatch, caplog):
    monkeypatch.setattr(rt, "kernel_source", lambda *files: SOURCE)
    monkeypatch.setattr(rt, "_noted", set())       # as in a fresh process: earlier tests built for this device
    options = (f"-DPLACE3D_NOTE_TEST={uuid.uuid4().int % 10**9}",)        # a build no cache has seen
    with caplog.at_level(logging.INFO, logger="place3d_kernels"):
        rt.build_program(ctx, ("probe.cl",), options)
    notes = [r.getMessage() for r in caplog.records if "compiling OpenCL kernels for" in r.getMessage()]
    assert len(notes) == 1 and "(first use; cached afterwards)" in notes[0], notes
    assert ctx.devices[0].name.strip() in notes[0]

    # the next process (no Program in memory, nothing noted yet) finds the build recorded: no note
    caplog.clear()
    rt._programs.clear()
    rt._noted.clear()
    with caplog.at_level(logging.INFO, logger="place3d_kernels"):
        rt.build_program(ctx, ("probe.cl",), options)
    assert not [r for r in caplog.records if "compiling OpenCL kernels" in r.getMessage()]
