"""The tuner's clock (hyqjax.studies.tune.clock.Clock): wall seconds less MuJoCo Warp's kernel build, plus the
compile charged, through pauses and a resume in another process."""
from __future__ import annotations

import pytest

from hyqjax.sim import warp_kernels
from hyqjax.studies.tune.clock import Clock


class Machine:
    """A wall clock and the process's kernel-build seconds, both moved by hand."""

    def __init__(self):
        self.wall, self.kernels = 100.0, 0.0

    def run(self, seconds: float, kernel_build: float = 0.0):
        self.wall += seconds
        self.kernels += kernel_build  # a build inside those seconds

    def clock(self) -> Clock:
        return Clock(timer=lambda: self.wall, kernel_seconds=lambda: self.kernels)


def test_the_kernel_build_is_left_out_and_counted_apart():
    m = Machine()
    m.run(3.0, kernel_build=1.0)  # before the clock starts: not the method's, not counted
    c = m.clock()
    m.run(10.0, kernel_build=4.0)  # the first generation builds the kernels: 4 of its 10 s
    c.charge(2.5)
    assert c.elapsed() == pytest.approx(10.0 - 4.0 + 2.5)
    assert c.kernel_build() == pytest.approx(4.0)
    m.run(5.0)
    assert c.elapsed() == pytest.approx(13.5) and c.kernel_build() == pytest.approx(4.0)


def test_a_pause_leaves_its_seconds_out_and_names_a_kernel_build_in_it():
    m = Machine()
    c = m.clock()
    m.run(2.0)
    before, kb = c.elapsed(), c.kernel_build()
    with c.paused():
        m.run(7.0, kernel_build=3.0)  # a resumed run compiling again, kernels included
    assert c.elapsed() == pytest.approx(before) and c.kernel_build() == pytest.approx(kb + 3.0)
    m.run(1.0, kernel_build=0.5)
    assert c.elapsed() == pytest.approx(before + 0.5) and c.kernel_build() == pytest.approx(3.5)
    state = c.state()  # and the next segment goes on from both
    c2 = Machine().clock()
    c2.restore(state)
    assert c2.elapsed() == pytest.approx(before + 0.5) and c2.kernel_build() == pytest.approx(3.5)


def test_a_resumed_clock_goes_on_and_adds_up_the_kernel_build_of_every_segment():
    m = Machine()
    c = m.clock()
    m.run(20.0, kernel_build=6.0)
    c.charge(1.0)
    c.physics_steps = 1234
    state = c.state()
    assert state["elapsed"] == pytest.approx(15.0) and state["kernel_build"] == pytest.approx(6.0)
    m2 = Machine()  # another process: its own wall clock and kernel counter
    m2.run(50.0, kernel_build=2.0)
    c2 = m2.clock()
    c2.restore(state)
    assert c2.elapsed() == pytest.approx(15.0) and c2.physics_steps == 1234 and c2.charged == 1.0
    m2.run(4.0, kernel_build=1.5)  # loading the cached kernels in the new process
    assert c2.elapsed() == pytest.approx(17.5) and c2.kernel_build() == pytest.approx(7.5)
    # a state stored before the kernel build was counted apart restores with none
    old = {k: v for k, v in state.items() if k != "kernel_build"}
    c3 = m2.clock()
    c3.restore(old)
    assert c3.elapsed() == pytest.approx(15.0) and c3.kernel_build() == 0.0


def test_the_default_clock_reads_the_process_kernel_build(monkeypatch):
    """The default source is :func:`hyqjax.sim.warp_kernels.seconds`, the sum of the module loads its hooks timed."""
    c = Clock()
    monkeypatch.setitem(warp_kernels._STATE, "seconds", warp_kernels._STATE["seconds"] + 30.0)
    assert c.kernel_build() == pytest.approx(30.0)
    assert c.elapsed() < 0.0  # 30 s left out of the few microseconds since the clock started


def test_a_resumed_study_keeps_the_compile_charges_it_first_measured():
    """A later process of a resumed study compiles its programs again, mostly from JAX's persistent cache; the
    study's record keeps what each program cost when first measured (what its runs were charged) and puts the
    later process's shorter measurement beside it, and a program first compiled in the later process is added."""
    from hyqjax.studies.tune.wallclock import record_charges

    res = dict(charges={})
    record_charges(res, {"gradient_windows": 40.3, "jacfwd/per_leg": 67.3, "forward": 4.9})
    record_charges(res, {"gradient_windows": 40.3, "jacfwd/per_leg": 67.3, "forward": 4.9})  # the same process again
    assert "charges_remeasured" not in res
    record_charges(res, {"gradient_windows": 19.1, "jacfwd/per_leg": 16.1, "forward": 4.9, "forward/final_3x544": 2.0})
    assert res["charges"] == {"gradient_windows": 40.3, "jacfwd/per_leg": 67.3, "forward": 4.9,
                              "forward/final_3x544": 2.0}
    assert res["charges_remeasured"] == {"gradient_windows": 19.1, "jacfwd/per_leg": 16.1}
