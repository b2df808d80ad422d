"""The job executor (core.runtime.parallel): process pool, Dask, interruption."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from proc_tree import descendants, still_alive

from core.runtime.parallel import JobError, check_scheduler, dask_jobs_per_task, run_jobs, use_scheduler
from core.runtime.progress import Cancelled

ROOT = Path(__file__).resolve().parents[1]


def _job(arg, common):
    """A deterministic job with some numpy work; common is shared by all jobs."""
    rng = np.random.default_rng(arg)
    m = rng.normal(size=(30, 30)) + common["shift"]
    return float(np.linalg.eigvalsh(m @ m.T).sum())


def _failing_job(arg, common):
    if arg == 3:
        raise ValueError("bad item three")
    return arg


def _slow_job(arg, common):
    time.sleep(0.15)
    return arg * arg, os.getpid()


@pytest.fixture(scope="module")
def local_cluster():
    """A LocalCluster for the module's tests; at the end its scratch folder (the scheduler's
    and the workers', one of a worker killed by a test among them) must be gone."""
    pytest.importorskip("distributed")
    import core.runtime.cluster as cluster

    made: list[str] = []
    mkdtemp = cluster.tempfile.mkdtemp

    def recorded(*args, **kwargs):
        made.append(mkdtemp(*args, **kwargs))
        return made[-1]

    cluster.tempfile.mkdtemp = recorded
    try:
        with use_scheduler("local:2") as client:
            cluster.tempfile.mkdtemp = mkdtemp
            # ours is the first (Dask makes its own inside it); in use by the cluster
            assert Path(made[0]).name.startswith("ssm-studio-dask-") and any(Path(made[0]).iterdir())
            yield client
    finally:
        cluster.tempfile.mkdtemp = mkdtemp
    assert not Path(made[0]).exists()


def test_pool_and_inline_give_the_same_results():
    items = [(f"item{i}", i) for i in range(12)]
    common = {"shift": 0.5}
    inline = run_jobs(_job, items, common=common, n_jobs=1)
    seen = []
    pooled = run_jobs(_job, items, common=common, n_jobs=2, window=3,
                      on_result=lambda key, value: seen.append(key) or value)
    assert inline == pooled and len(inline) == 12
    assert sorted(seen) == sorted(k for k, _ in items)


def test_job_error_names_the_job():
    with pytest.raises(JobError, match="3.*bad item three"):
        run_jobs(_failing_job, [(i, i) for i in range(6)], n_jobs=2)


def test_cancel_from_progress_stops_the_pool():
    calls = []

    def progress(fraction, message):
        calls.append(fraction)
        raise Cancelled()

    with pytest.raises(Cancelled):
        run_jobs(_slow_job, [(i, i) for i in range(40)], n_jobs=2, progress=progress)
    assert len(calls) == 1


def test_scheduler_option_is_validated():
    assert check_scheduler("local:3") == "local:3"
    assert check_scheduler("tcp://10.0.0.1:8786") == "tcp://10.0.0.1:8786"
    for bad in ("local:0", "local:x", "a b"):
        with pytest.raises(ValueError, match="--scheduler"):
            check_scheduler(bad)


def test_dask_gives_the_pool_results(local_cluster):
    items = [(i, i) for i in range(16)]
    common = {"shift": -0.25}
    pooled = run_jobs(_job, items, common=common, n_jobs=2)
    on_dask = run_jobs(_job, iter(items), common=common, total=len(items), window=4)
    assert on_dask == pooled


def test_dask_job_error_names_the_job(local_cluster):
    with pytest.raises(JobError, match="bad item three"):
        run_jobs(_failing_job, [(i, i) for i in range(6)])


def _quick_job_and_its_task(arg, common):
    from distributed import get_worker

    if arg == common:
        raise ValueError(f"bad item {arg}")
    return arg * arg, get_worker().get_current_task()


def test_dask_puts_short_jobs_several_to_a_task(local_cluster):
    """Jobs of a millisecond go several to a Dask task (its overhead would dominate); every
    job still has its own result, and a failing job in a batch is named by its own key."""
    results = run_jobs(_quick_job_and_its_task, [(i, i) for i in range(60)], common=-1)
    assert {k: v[0] for k, v in results.items()} == {i: i * i for i in range(60)}
    jobs_per_task = np.unique([task for _, task in results.values()], return_counts=True)[1]
    assert len(jobs_per_task) < 30 and jobs_per_task.max() > 1
    with pytest.raises(JobError, match="job 50 failed.*bad item 50"):
        run_jobs(_quick_job_and_its_task, [(i, i) for i in range(60)], common=50)


def test_jobs_per_dask_task():
    assert dask_jobs_per_task(None, 100, 2) == 1  # nothing timed yet
    assert dask_jobs_per_task(2.0, 100, 2) == 1  # long jobs: one per task
    assert dask_jobs_per_task(0.1, 100, 2) == 5  # 0.5 s of compute per task
    assert dask_jobs_per_task(0.001, 10_000, 2) == 32  # capped
    assert dask_jobs_per_task(0.01, 6, 2) == 2  # the last tasks stay short
    assert dask_jobs_per_task(0.01, None, 2) == 32  # unknown total


def test_dask_run_survives_a_killed_worker(local_cluster):
    """A worker process is SIGKILLed mid-run: its jobs are rescheduled, every result arrives."""
    client = local_cluster
    worker_pids = client.run(os.getpid)
    killed = []

    def on_result(key, value):
        if not killed:  # first result in: kill the worker that is not the one that sent it
            victim = next(p for p in worker_pids.values() if p != value[1])
            os.kill(victim, signal.SIGKILL)
            killed.append(victim)
        return value[0]

    items = [(i, i) for i in range(24)]
    results = run_jobs(_slow_job, items, on_result=on_result, window=8)
    assert killed
    assert results == {i: i * i for i in range(24)}


_SCRIPT = textwrap.dedent("""
    import sys, time
    from core.runtime.parallel import run_jobs, termination_signals, Terminated
    import helper_jobs

    with termination_signals():
        done = []
        try:
            run_jobs(helper_jobs.sleepy, [(i, i) for i in range(200)], n_jobs=2,
                     on_result=lambda k, v: (done.append(k), print("done", k, flush=True)))
        except Terminated as exc:
            print("stopped after", len(done), flush=True)
            sys.exit(exc.exit_code)
""")


def _finish(proc: subprocess.Popen, guard: float, hung: str) -> tuple[str, str]:
    """The script's stdout and stderr once it ends; fails with ``hung`` if it has not ended
    after ``guard`` seconds (a hang guard, not a timing assertion)."""
    try:
        return proc.communicate(timeout=guard)
    except subprocess.TimeoutExpired:
        proc.kill()
        pytest.fail(hung)


def _start_script(tmp_path: Path, script: str, jobs_source: str) -> subprocess.Popen:
    """``python -c script`` with a module ``helper_jobs`` (``jobs_source``) importable."""
    (tmp_path / "helper_jobs.py").write_text(jobs_source)
    env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}{tmp_path}")
    return subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)


def test_sigterm_stops_the_pool_and_leaves_no_worker(tmp_path):
    proc = _start_script(tmp_path, _SCRIPT, "import time\n\ndef sleepy(arg, common):\n"
                                            "    time.sleep(0.3)\n    return arg\n")
    try:
        first = proc.stdout.readline()  # a job finished: workers are up and busy
        assert first.startswith("done"), proc.stderr.read()
        workers = descendants(proc.pid)
        assert len(workers) >= 2
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)  # a hang guard, not a timing assertion
    finally:
        proc.kill()
    assert proc.returncode == 143, err
    assert "stopped after" in out
    assert still_alive(workers) == []


_INTERRUPTED_WAIT_SCRIPT = textwrap.dedent("""
    import os, signal, sys
    import concurrent.futures._base as futures_base
    from core.runtime.parallel import run_jobs, termination_signals
    import helper_jobs

    take_all = futures_base._AcquireFutures.__enter__
    calls = []

    def take_one_then_sigint(self):
        # SIGINT arrives while wait() holds the first future's lock and not yet the others
        calls.append(1)
        if len(calls) == 3:
            self.futures[0]._condition.acquire()
            os.kill(os.getpid(), signal.SIGINT)
            for future in self.futures[1:]:
                future._condition.acquire()
            return
        take_all(self)

    futures_base._AcquireFutures.__enter__ = take_one_then_sigint
    with termination_signals():
        try:
            run_jobs(helper_jobs.sleepy, [(i, i) for i in range(40)], n_jobs=2)
        except KeyboardInterrupt:
            print("stopped", flush=True)
            sys.exit(130)
""")


def test_a_sigint_inside_the_pools_wait_stops_it(tmp_path):
    """A SIGINT landing while ``concurrent.futures.wait`` takes its futures' locks one by one:
    the pool still stops and the process exits 130 (raised there, it left a lock held, and
    loky's result thread, then the pool's shutdown, waited on it for good)."""
    proc = _start_script(tmp_path, _INTERRUPTED_WAIT_SCRIPT,
                         "import time\n\ndef sleepy(arg, common):\n"
                         "    time.sleep(0.3)\n    return arg\n")
    out, err = _finish(proc, 60, "the pool did not stop after a SIGINT inside its wait")
    assert proc.returncode == 130, err
    assert "stopped" in out and "Traceback" not in err


_CANCEL_SCRIPT = textwrap.dedent("""
    import numpy as np
    from core.runtime.parallel import run_jobs
    from core.runtime.progress import Cancelled
    import helper_jobs

    big = np.arange(4_000_000, dtype=float)  # 32 MB a job: far more than a pipe holds
    seen = []

    def progress(fraction, message):
        if fraction > 0:  # the first result is in: Cancel while jobs fill the call queue
            raise Cancelled()

    try:
        run_jobs(helper_jobs.total, [(i, big) for i in range(24)], n_jobs=2, window=12,
                 progress=progress, on_result=lambda k, v: seen.append(v) or v)
    except Cancelled:
        print("cancelled after", len(seen), "sum ok", seen[0] == big.sum(), flush=True)
""")


def test_a_pool_cancelled_with_large_jobs_queued_lets_the_process_exit(tmp_path):
    """Cancel while the pool's call queue is still feeding large jobs to workers that are then
    killed: the run stops, and the process exits (a feeder thread blocked on the pipe would
    keep the interpreter from ending)."""
    proc = _start_script(tmp_path, _CANCEL_SCRIPT, "import time\n\ndef total(arg, common):\n"
                                                   "    time.sleep(0.2)\n    return float(arg.sum())\n")
    out, err = _finish(proc, 120, "the process did not exit after a cancelled pool")
    assert proc.returncode == 0, err
    assert "sum ok True" in out and 1 <= int(out.split()[2]) < 24
    assert "Traceback" not in err and "leaked" not in err


@pytest.fixture(scope="module")
def small_meshes():
    """Five known-homology beans of ~120 vertices, own tessellations and poses."""
    from core.datasets.shapes import known_homology_shapes

    return known_homology_shapes("bean", 5, seed=3, n_points=(100, 140)).meshes


def test_correspondence_on_dask_equals_the_pool(local_cluster, small_meshes):
    from core.correspondence import establish_correspondence

    with use_scheduler(None):  # the process pool, even inside the cluster fixture
        pooled = establish_correspondence(small_meshes, 0, n_jobs=2)
    streamed = {}
    on_dask = establish_correspondence(small_meshes, 0,
                                       on_shape=lambda i, m: streamed.__setitem__(i, m))  # last call: kept
    assert sorted(streamed) == list(range(len(small_meshes)))
    for i, (a, b) in enumerate(zip(pooled.meshes, on_dask.meshes)):
        np.testing.assert_array_equal(a.vertices, b.vertices)  # byte-identical
        np.testing.assert_array_equal(streamed[i].vertices, b.vertices)  # streamed = final
        np.testing.assert_array_equal(streamed[i].faces, on_dask.faces)
    assert pooled.residuals_mm == on_dask.residuals_mm


def test_streamed_correspondence_on_dask_reads_the_inputs_in_the_workers(local_cluster,
                                                                        small_meshes, tmp_path):
    """The command line's mode on Dask: the (daemonic) worker processes read each input file
    in a child of their own and write the groomed inputs into the scratch folder; the
    streamed results equal the in-memory ones, bit for bit, and the scratch is removed."""
    from core.correspondence import establish_correspondence
    from core.io import save_mesh

    paths = []
    for i, mesh in enumerate(small_meshes):
        paths.append(tmp_path / f"bean{i}.vtk")
        save_mesh(paths[-1], mesh)
    with use_scheduler(None):
        from core.io import load_mesh

        pooled = establish_correspondence([load_mesh(p) for p in paths], 0, n_jobs=1)
    streamed = {}
    on_dask = establish_correspondence(paths, 0, scratch=tmp_path / "scratch", keep_meshes=False,
                                       on_shape=lambda i, m: streamed.__setitem__(i, m))  # last call: kept
    assert sorted(streamed) == list(range(len(paths))) and not (tmp_path / "scratch").exists()
    for i, mesh in enumerate(pooled.meshes):
        assert streamed[i].vertices.tobytes() == mesh.vertices.tobytes()
    assert pooled.residuals_mm == on_dask.residuals_mm


def test_evaluation_on_dask_equals_the_pool(local_cluster, small_meshes):
    from core.evaluation import evaluate_model

    rng = np.random.default_rng(0)
    base = small_meshes[0].vertices
    shapes = np.stack([base * rng.uniform(0.9, 1.1, 3) + rng.normal(0, 0.2, base.shape)
                       for _ in range(5)])
    measures = ("generalisation", "sparse_reconstruction")
    with use_scheduler(None):
        pooled = evaluate_model("pca", shapes, None, measures=measures, n_jobs=2)
        inline = evaluate_model("pca", shapes, None, measures=measures, n_jobs=1)
    on_dask = evaluate_model("pca", shapes, None, measures=measures)
    for m in measures:
        for run in (pooled, on_dask):
            np.testing.assert_array_equal(run[m]["avg"], inline[m]["avg"])
            np.testing.assert_array_equal(run[m]["max"], inline[m]["max"])
    assert np.all(inline["generalisation"]["avg"] > 0)  # real leave-one-out errors


def test_cluster_started_with_the_dask_command_line(tmp_path):
    """A user's cluster: `dask scheduler` + `dask worker --nworkers 2 --nthreads 1` as separate
    processes; run_jobs on it equals the pool, and a worker SIGKILLed mid-run costs nothing."""
    pytest.importorskip("distributed")
    dask_cli = Path(sys.executable).with_name("dask")
    if not dask_cli.exists():
        pytest.skip("the dask command line is not installed")
    (tmp_path / "cli_jobs.py").write_text("import os, time\n\ndef square(arg, common):\n"
                                          "    time.sleep(0.1)\n    return arg * arg + common, os.getpid()\n")
    # the user's cluster keeps its scratch space (dask-scratch-space) in the test's folder
    env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}{tmp_path}", TMPDIR=str(tmp_path))
    sched_file = tmp_path / "scheduler.json"
    common = ["--no-dashboard"]
    procs = [subprocess.Popen([str(dask_cli), "scheduler", "--scheduler-file", str(sched_file),
                               "--port", "0", *common], env=env, start_new_session=True,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    procs.append(subprocess.Popen([str(dask_cli), "worker", "--scheduler-file", str(sched_file),
                                   "--nworkers", "2", "--nthreads", "1", *common], env=env,
                                  start_new_session=True, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL))
    sys.path.insert(0, str(tmp_path))
    try:
        import cli_jobs

        deadline = time.monotonic() + 60  # a hang guard
        while not sched_file.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        import json

        address = json.loads(sched_file.read_text())["address"]
        items = [(i, i) for i in range(16)]
        with use_scheduler(None):  # the process pool, even inside another test's cluster
            pooled = run_jobs(cli_jobs.square, items, common=3, n_jobs=2)
        with use_scheduler(address) as client:
            client.wait_for_workers(2, timeout=60)
            worker_pids = list(client.run(os.getpid).values())
            killed = []

            def on_result(key, value):
                if not killed:  # the first result is in: kill the other worker
                    victim = next(p for p in worker_pids if p != value[1])
                    os.kill(victim, signal.SIGKILL)
                    killed.append(victim)
                return value

            on_dask = run_jobs(cli_jobs.square, items, common=3, on_result=on_result, window=8)
        assert killed
        assert {k: v[0] for k, v in on_dask.items()} == {k: v[0] for k, v in pooled.items()}
        assert {k: v[0] for k, v in pooled.items()} == {i: i * i + 3 for i in range(16)}
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop("cli_jobs", None)
        for p in procs:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=30)


def test_a_job_error_is_one_line_on_the_command_line(capsys):
    """A job failing in a worker (not a per-shape problem the job reports itself) ends the
    command with one line naming the job, exit 2, not a traceback."""
    import argparse

    from core.cli import run_command

    def command(args):
        return run_jobs(_failing_job, [(i, i) for i in range(6)], n_jobs=1)

    code = run_command(argparse.Namespace(_run=command, _command="correspond"))
    err = capsys.readouterr().err
    assert code == 2
    assert err.strip().count("\n") == 0 and "job 3 failed" in err and "bad item three" in err


def test_a_job_failure_from_data_is_one_line_and_a_bug_keeps_its_traceback():
    """Batches report failed items and go on: bad data is one line, a programming error
    carries its traceback into the report instead of passing for a bad shape."""
    from core.runtime.failures import describe_failure

    assert describe_failure(ValueError("singular geometry")) == "ValueError: singular geometry"
    try:
        [][1]
    except IndexError as exc:
        text = describe_failure(exc)
    assert text.startswith("internal error") and "IndexError" in text
    assert "Traceback" in text and "test_parallel.py" in text


def test_a_signal_landing_in_a_finalizer_is_raised_at_the_next_wait_not_inside_it():
    """A SIGINT arriving while a semaphore's finalizer runs (the garbage collector runs them
    wherever it is triggered): raised there, it was swallowed with a printed traceback and cut
    the cleanup in half (the semaphore unlinked, still registered: the resource tracker
    warned of a leak at exit). The finalizer now completes and the next wait raises it."""
    from multiprocessing import util

    from core.runtime.parallel import raise_if_signalled, termination_signals

    class Resource:
        pass

    steps: list[str] = []

    def cleanup() -> None:
        steps.append("unlinked")
        os.kill(os.getpid(), signal.SIGINT)  # the handler runs at the next bytecode
        for _ in range(1000):
            pass
        steps.append("unregistered")

    with termination_signals():
        resource = Resource()
        util.Finalize(resource, cleanup, exitpriority=0)
        del resource  # the finalizer runs here, as a weakref callback
        assert steps == ["unlinked", "unregistered"]
        with pytest.raises(KeyboardInterrupt):
            raise_if_signalled()
