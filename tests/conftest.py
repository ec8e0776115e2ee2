"""Shared fixtures of the hyqjax test suite (CPU-sized; every test jits what it calls)."""
from __future__ import annotations

import atexit
import gc
import os
import shutil
import subprocess
import sys
import tempfile
import textwrap
import warnings

#: The session's XLA:CPU options (XLA_FLAGS, set before jax is imported, inherited by every subprocess a test
#: starts unless it gives XLA_FLAGS itself): XLA:CPU's elemental emitters instead of its fusion emitters, the code
#: generator hyqjax already compiles the C MuJoCo backend's programs with (``hyqjax.sim.cpu_backend.
#: COMPILER_OPTIONS``), and LLVM's optimisation level 0 for the compiled code. The suite is nearly all XLA compiling
#: MJX programs on the CPU and running them for a few hundred ticks; the first option takes about a quarter off the
#: suite's CPU time, the second a further tenth (benchmarks/RESULTS.md), and every test passes unchanged with both.
#: The third compiles each program's LLVM module in one piece instead of XLA:CPU's default 32 parts on a thread
#: pool: with two xdist workers on 2 cores the pool finds no idle core, and the split itself costs CPU. Alone, the
#: same files with and without it, alternated on the shared 2-core VM (2026-11-29, load 1-4): test_bounding.py
#: 101.0 / 91.8 s against 111.9 / 102.5 s (96 / 90 s of user CPU against 107 / 99 s); test_tune.py's three
#: largest closed-loop tests 151.0 s against 160.8 s (152 against 167 s of user CPU; XLA of the reverse-mode program
#: 31.8 against 37.4 s); test_model, test_sim, test_stepdown and test_cpu_backend 240.6 s against 229.6 s of wall
#: under a higher load, 207 against 217 s of user CPU; every test run there passes with it. (An earlier pair of
#: whole-suite runs, benchmarks/RESULTS.md "XLA's codegen split", was inside the machine's drift.)
#: What a user's process compiles with (XLA's defaults) still runs here: the two-device rollout of
#: tests/test_sim.py, compared with the session's run of the same scenario, and its batch-512 deadlock regression
#: (:func:`user_xla_flags`).
SESSION_XLA_FLAGS = ("--xla_cpu_use_fusion_emitters=false", "--xla_backend_optimization_level=0",
                     "--xla_cpu_parallel_codegen_split_count=1")
if "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):  # a choice of the user's is kept
    os.environ["XLA_FLAGS"] = " ".join([os.environ.get("XLA_FLAGS", ""), *SESSION_XLA_FLAGS]).strip()
    os.environ["HYQJAX_TEST_XLA_FLAG"] = " ".join(SESSION_XLA_FLAGS)  # added here (the xdist workers inherit both)

#: The user's own presets (hyqjax.presets.registry.user_dir) of this test session: an empty directory of its own,
#: so that no test reads or writes the real home's (~/.local/share/hyqjax/presets); subprocesses inherit it. A test
#: that saves presets points HYQJAX_PRESETS_DIR at its tmp_path.
os.environ["HYQJAX_PRESETS_DIR"] = tempfile.mkdtemp(prefix="hyqjax-test-presets-")
atexit.register(shutil.rmtree, os.environ["HYQJAX_PRESETS_DIR"], True)

import hyqjax  # noqa: E402,F401  (sets the XLA:CPU flags before jax is imported)
import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def user_xla_flags() -> str:
    """XLA_FLAGS as a user's process has them: this session's without the options it added (``SESSION_XLA_FLAGS``)."""
    added = set(os.environ.get("HYQJAX_TEST_XLA_FLAG", "").split())
    return " ".join(f for f in os.environ.get("XLA_FLAGS", "").split() if f not in added)


# A persistent compilation cache for this test session only (fresh each run, removed at exit): the
# same program compiled twice (hyqjax.sim.rollout.batch_rollout jits a new closure on every call) is compiled
# once. Subprocesses started by run_python/start_python share it. A cache set by the user is kept: JAX's own
# variable, or hyqjax's (the directory every hyqjax command a test runs, in this process or another, uses; with the
# session in another directory, a test that ran a command in-process would have moved its worker's programs there).
if not os.environ.get("JAX_COMPILATION_CACHE_DIR") and os.environ.get("HYQJAX_CACHE_DIR"):
    from hyqjax.io.cache import cache_dir

    os.makedirs(cache_dir(), exist_ok=True)
    os.environ["JAX_COMPILATION_CACHE_DIR"] = cache_dir()
if not os.environ.get("JAX_COMPILATION_CACHE_DIR"):
    _CACHE_DIR = tempfile.mkdtemp(prefix="hyqjax-test-jax-cache-")
    atexit.register(shutil.rmtree, _CACHE_DIR, ignore_errors=True)
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _CACHE_DIR
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])


_RUNNING: dict[str, pytest.Item] = {}


def pytest_configure(config):
    """The unit lane (``pytest -m "not slow"``) compiles no MJX model: there, building one (``mjx.put_model``)
    in a test without the ``slow`` mark, or in a fixture it uses, fails at once naming the test and the fix."""
    if "not slow" not in (config.getoption("-m") or ""):
        return
    from mujoco import mjx

    put_model = mjx.put_model

    def guarded(*args, **kwargs):
        item = _RUNNING.get("item")
        if item is not None and item.get_closest_marker("slow") is None:
            raise RuntimeError(f"{item.nodeid} builds an MJX model (mjx.put_model) in the unit lane: "
                               "mark it @pytest.mark.slow")
        return put_model(*args, **kwargs)

    mjx.put_model = guarded


def pytest_runtest_setup(item):
    _RUNNING["item"] = item


def pytest_unconfigure(config):
    """A pytest-xdist worker ends without the interpreter's finalization (:func:`_end_worker`)."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        atexit.register(_end_worker)  # registered last: runs first


def _end_worker():
    """End an xdist worker process at once (``os._exit``) once it exits: by then its session is over and the
    controller, which has every report, has asked it to stop. Finalizing the interpreter would free the thousands
    of compiled XLA programs a worker holds at the end of the suite (several GB) and tear down JAX's CPU client and
    MuJoCo Warp's modules: about 6 s at the end of the suite, with nothing else running (benchmarks/RESULTS.md,
    "Ending the xdist workers without finalization")."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def _memory_map_count() -> int | None:
    """Memory mappings of this process (Linux), else None."""
    try:
        with open("/proc/self/maps") as f:
            return sum(1 for _ in f)
    except OSError:
        return None


def _max_map_count() -> int | None:
    try:
        with open("/proc/sys/vm/max_map_count") as f:
            return int(f.read())
    except (OSError, ValueError):
        return None


#: Memory mappings (a share of ``vm.max_map_count``) above which a finished test module's compiled programs are
#: released (:func:`_release_compiled_programs`).
RELEASE_AT = 0.4


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_programs():
    """Drop JAX's compiled programs after a test module once the process holds many of them.

    Every XLA:CPU program loaded in a process holds three memory mappings per compiled object (code,
    constants, data), and JAX keeps a program for as long as its jitted function lives (module-level functions
    and hyqjax's own caches live for the whole session). In one pytest process over the whole suite
    with warp-lang installed (test_stepdown's warp test runs in-process) the count grew to 53,600 by the middle
    of test_tune, and its next gradient program took it to the kernel's per-process limit
    (``vm.max_map_count``, 65,530 by default): LLVM's mmap failed ("LLVM compilation error: Cannot allocate
    memory") and the session died of SIGABRT or SIGSEGV. One module needs at most 12,624 mappings, so after a
    module the programs are released once the count passes ``RELEASE_AT`` of the limit (26,212 by default), and
    kept below it: a later module that runs a program an earlier one ran (hyqjax caches its rollouts per static
    configuration) then neither traces, lowers nor loads it again. A released program that a later module needs
    again is loaded from the session's persistent compilation cache (traced and lowered anew).
    """
    yield
    n, limit = _memory_map_count(), _max_map_count()
    if n is not None and limit is not None and n <= RELEASE_AT * limit:
        return
    gc.collect()
    jax.clear_caches()
    gc.collect()
    n = _memory_map_count()
    if n is not None and limit is not None and n > 0.6 * limit:
        warnings.warn(f"{n} memory mappings after this module's JAX caches were cleared (vm.max_map_count "
                      f"{limit}): something outside JAX's caches keeps compiled programs alive", stacklevel=1)


@pytest.fixture
def x64():
    """Run the test with 64-bit JAX types, restoring the previous setting afterwards."""
    with jax.enable_x64(True):
        yield


@pytest.fixture(scope="session")
def hyq():
    """The compiled default HyQ + terrain ``MjModel`` and its named ids."""
    from hyqjax.sim import model as hmodel

    m = hmodel.load_model()
    return m, hmodel.model_ids(m)


@pytest.fixture
def rng():
    return np.random.default_rng(0)


#: XLA:CPU options of a test's long MJX-JAX runs (tests/test_cpu_backend.py, tests/test_stepdown.py): LLVM at level 2
#: instead of the session's 0. A 24 s step-down run in chunks of 0.6 s is 40 calls of one chunk program, which runs
#: about 4 times faster at level 2 while compiling in about twice the time (benchmarks/RESULTS.md).
LONG_RUN_OPTIONS = {"xla_backend_optimization_level": 2}


def compiled_for_long_runs(ro, monkeypatch):
    """The rollout ``ro`` with its runner compiling at :data:`LONG_RUN_OPTIONS` for the calling test."""
    monkeypatch.setattr(ro.runner(), "compiler_options", LONG_RUN_OPTIONS)
    return ro


def run_python(code: str, timeout: float, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh Python (repo root on the path) and return the finished process.

    A ``subprocess.TimeoutExpired`` (a hang, e.g. a deadlock) propagates and fails the calling test.
    """
    full_env = dict(os.environ)
    full_env["PYTHONPATH"] = REPO_ROOT + os.pathsep + full_env.get("PYTHONPATH", "")
    full_env.update(env or {})
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=REPO_ROOT, env=full_env,
                          capture_output=True, text=True, timeout=timeout)


def start_python(code: str, env: dict[str, str] | None = None, log: str | None = None) -> subprocess.Popen:
    """Start ``code`` in a fresh Python in the background (see :func:`run_python`); ``.communicate(timeout=...)`` it.

    ``log``: a file that takes the process's stdout and stderr instead of pipes, for a caller that waits on
    something else than the process's output (a pipe nobody reads blocks the process once its 64 KiB are full:
    XLA:CPU logs two error lines of about 1.7 kB per program loaded from the persistent cache on hosts whose
    compile-time features it does not recognise, such as AMD EPYC)."""
    full_env = dict(os.environ)
    full_env["PYTHONPATH"] = REPO_ROOT + os.pathsep + full_env.get("PYTHONPATH", "")
    full_env.update(env or {})
    out = subprocess.PIPE if log is None else open(log, "w")
    try:
        return subprocess.Popen([sys.executable, "-c", textwrap.dedent(code)], cwd=REPO_ROOT, env=full_env,
                                stdout=out, stderr=subprocess.PIPE if log is None else subprocess.STDOUT, text=True)
    finally:
        if log is not None:
            out.close()
