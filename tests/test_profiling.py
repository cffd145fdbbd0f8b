"""profiling.section / profile: off by default, nested accumulation, the table the CLI prints."""

import io
import time

from place3d_kernels import profiling


def test_section_is_a_no_op_outside_a_profile():
    assert not profiling.enabled()
    with profiling.section("x"):
        pass
    assert not profiling.enabled()


def test_profile_accumulates_nested_sections_and_prints_a_table():
    out = io.StringIO()
    with profiling.profile(out=out) as p:
        assert profiling.enabled()
        for _ in range(3):
            with profiling.section("outer"):
                with profiling.section("inner"):
                    time.sleep(0.002)
    assert not profiling.enabled()
    assert p.totals[("outer",)][1] == 3 and p.totals[("outer", "inner")][1] == 3
    assert p.totals[("outer",)][0] >= p.totals[("outer", "inner")][0] >= 0.006
    text = out.getvalue()
    lines = text.splitlines()
    outer = next(i for i, s in enumerate(lines) if s.startswith("outer"))
    assert lines[outer + 1].startswith("  inner")
    assert "total (profile span)" in text


def test_cli_profile_flag_prints_the_table(capsys):
    from place3d_app.cli import main

    assert main(["--profile", "backends"]) == 0
    err = capsys.readouterr().err
    assert "place3d profile" in err and "total (profile span)" in err


def test_record_adds_a_span_measured_elsewhere_under_the_open_section():
    from place3d_kernels.profiling import profile, record, section

    record("outside", 1.0)                              # no profile running: nothing to add to
    with profile(print_table=False) as p:
        with section("parent"):
            record("child step", 0.25)
            record("child step", 0.5)
        record("top", 2.0)
    assert p.totals[("parent", "child step")] == [0.75, 2]
    assert p.totals[("top",)] == [2.0, 1]
    assert not any("outside" in k for k in p.totals)
    assert "    child step" not in p.table() and "  child step" in p.table()


def test_spans_say_when_a_section_was_first_entered_and_last_left():
    # a section entered twice with a gap: its span runs from the first entry to the last exit, longer than its
    # seconds; a thread's section beside it overlaps it; the table prints both numbers per row
    import threading

    from place3d_kernels.profiling import profile, section

    with profile(print_table=False) as p:
        with section("twice"):
            time.sleep(0.02)
        time.sleep(0.05)

        def beside():
            with section("thread"):
                time.sleep(0.03)

        th = threading.Thread(target=beside)
        th.start()
        with section("twice"):
            time.sleep(0.02)
        th.join()
    first, last = p.spans[("twice",)]
    assert 0.0 <= first < 0.01 and last - first >= 0.09 > p.totals[("twice",)][0]
    t0, t1 = p.spans[("thread",)]
    assert first + 0.06 <= t0 < t1 <= p.wall and t1 - t0 >= 0.03
    row = next(r for r in p.table().splitlines() if r.startswith("twice"))
    assert row.split()[-2:] == [f"{first:.2f}", f"{last:.2f}"]


def test_a_repeated_section_reports_its_median_and_slowest_call():
    """A section entered ``REPEATED`` times or more gets a line below the table: the median call, the slowest
    call and when it began, and the calls over ``SLOW`` times the median; sections entered fewer times get
    none."""
    with profiling.profile(print_table=False) as p:
        for i in range(profiling.REPEATED):
            with profiling.section("loop"):
                time.sleep(0.06 if i == 5 else 0.002)
        with profiling.section("once"):
            for _ in range(profiling.REPEATED):
                with profiling.section("loop"):     # the same name under another parent: its own line
                    pass
    lines = p.table().splitlines()
    (row,) = [ln for ln in lines if ln.startswith("  loop ") and " median " in ln]
    words = row.split()
    median, slowest, at, slow = float(words[2]), float(words[4]), float(words[6]), int(words[-1])
    assert 2.0 <= median < 10.0 and slowest >= 60.0 and slow == 1
    start, seconds = max(p.calls[("loop",)], key=lambda c: c[1])
    assert at == round(start, 2) and abs(seconds * 1e3 - slowest) < 0.051      # as printed: 0.1 ms, 0.01 s
    assert 5 * 0.002 <= start < 0.5
    named = [ln.split(" median ")[0].strip() for ln in lines if " median " in ln]
    assert named == ["loop", "once / loop"]          # "once", entered once, gets no line
    assert lines[lines.index(row) - 1].startswith("calls of sections entered")
