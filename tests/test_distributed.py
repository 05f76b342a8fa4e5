"""Power maps on Dask distributed (issue 15): one task per chunk on worker processes, the same
numbers as one process, fault tolerant (a killed worker, a killed client, damaged parts).

One module-scoped ``LocalCluster(n_workers=2, processes=True, threads_per_worker=1)``: two
worker processes with one JAX CPU device each, like the suite's single process, so a chunk runs
the same compiled program (same chunk size, one device) in both and the maps are equal bit for
bit. Workers share a JAX compilation cache (tmp dir) so a restarted worker does not recompile.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import jaxdea
import jaxdea.studies.powermap as pm
from jaxdea.cli import main
from jaxdea.cli.args import parse_points, parse_range
from jaxdea.engine.sharding import MULTI_OUTPUT_FUSION, with_extra_option
from jaxdea.studies.distributed import MIN_CLUSTER_CHUNK, cluster_units
from jaxdea.studies.mapstore import PartWarning, open_map

distributed = pytest.importorskip("distributed")

ROOT = Path(__file__).resolve().parents[1]
CONFIG = str(ROOT / "configs" / "dcdea_ls.toml")
SMALL = ["--mass", "1e-3:2e-3:2", "--damping", "0.05:0.1:2", "--freq", "60:200:20"]  # 32 cells
LONG = ["--mass", "1e-3:2e-3:2", "--damping", "0.05:0.1:2", "--freq", "60:200:3.5"]  # 164
RUN = dict(cycles=10, average=2, chunk_cells=4, progress=False)
CLI_RUN = ["--cycles", "10", "--average", "2", "--chunk", "4", "--no-progress"]


def _axes(grid: list[str]) -> dict:
    return dict(mass=parse_points(grid[1], "--mass"), damping=parse_points(grid[3], "--damping"),
                freq=parse_range(grid[5]))


@pytest.fixture(scope="module")
def model():
    return jaxdea.load_config(CONFIG)


@pytest.fixture(scope="module")
def small_ref(model):  # this process: one JAX device, 4-cell chunks
    return pm.powermap(model, **_axes(SMALL), **RUN)


@pytest.fixture(scope="module")
def long_ref(model):
    return pm.powermap(model, **_axes(LONG), **RUN)


@pytest.fixture(scope="module")
def jax_cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp("jax_cache"))


@pytest.fixture(scope="module")
def client(jax_cache):
    old = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = jax_cache  # the worker processes inherit it
    cluster = client = None
    try:
        cluster = distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1,
                                           dashboard_address=None)
        client = distributed.Client(cluster, timeout=60)
        client.wait_for_workers(2, timeout=60)
        yield client
    finally:
        if client is not None:
            client.close(timeout=30)
        if cluster is not None:
            cluster.close(timeout=30)
        if old is None:
            os.environ.pop("JAX_COMPILATION_CACHE_DIR", None)
        else:
            os.environ["JAX_COMPILATION_CACHE_DIR"] = old


def _same_map(ds: xr.Dataset, ref: xr.Dataset) -> None:
    """Every variable equal bit for bit (NaN where NaN), every attribute but the per-call
    chunk counts equal."""
    skip = ("chunks_computed", "chunks_reused")
    assert {k: v for k, v in ds.attrs.items() if k not in skip} == \
        {k: v for k, v in ref.attrs.items() if k not in skip}
    assert set(ds.variables) == set(ref.variables)
    for k in ref.variables:
        np.testing.assert_array_equal(ds[k].values, ref[k].values, err_msg=k)


def _wait_parts(parts: Path, n: int, proc=None, limit: float = 240) -> int:
    t0 = time.time()
    while (done := len(list(parts.glob("chunk_*.npz")))) < n:
        assert proc is None or proc.poll() is None, proc.communicate() if proc else None
        assert time.time() - t0 < limit, "no chunk part written in time"
        time.sleep(0.005)
    return done


def test_cluster_map_equals_the_single_process_map_bit_for_bit(model, small_ref, client,
                                                               tmp_path):
    store = tmp_path / "m.zarr"
    ds = pm.powermap(model, **_axes(SMALL), **RUN, client=client, store=store)
    assert ds.attrs["chunks_computed"] == 8 and ds.attrs["chunks_reused"] == 0
    _same_map(ds, small_ref)
    _same_map(open_map(store), small_ref)
    assert not Path(str(store) + ".parts").exists()
    # without a store the receipts carry the arrays
    _same_map(pm.powermap(model, **_axes(SMALL), **RUN, client=client), small_ref)


def test_cli_on_an_existing_scheduler_equals_the_single_process_map(small_ref, client,
                                                                    tmp_path, capsys):
    """``jaxdea powermap --scheduler ADDRESS``: the CLI connects to a running cluster (here the
    module's, by its scheduler's address, as a SLURM user would pass theirs) and writes the
    same map bit for bit."""
    store = tmp_path / "m.zarr"
    rc = main(["powermap", CONFIG, *SMALL, *CLI_RUN, "--out", str(store),
               "--scheduler", client.scheduler.address])
    assert rc == 0, capsys.readouterr().err
    assert "Dask cluster tcp://" in capsys.readouterr().out
    _same_map(open_map(store), small_ref)



def test_a_warm_started_map_on_the_cluster_equals_the_single_process_map(model, client):
    """``start="neighbour"`` chunks (whole masses, a chain each) on the workers: the same map
    bit for bit, its per-cell ``coexist`` flag included (carried in each chunk's receipt)."""
    kw = dict(**_axes(SMALL), protocol="periodic", start="neighbour", chunk_cells=16,
              progress=False)
    ref = pm.powermap(model, **kw)
    assert "coexist" in ref and (ref.status == 0).all()
    _same_map(pm.powermap(model, **kw, client=client), ref)


def test_cluster_chunk_rule():
    assert cluster_units(100_000, 1, 2, 4096) == 4096  # capped at the single-process chunk
    assert cluster_units(10_000, 1, 2, 4096) == 1250  # ~4 chunks per worker
    assert cluster_units(1000, 1, 2, 4096) == MIN_CLUSTER_CHUNK  # no tiny tasks
    assert cluster_units(32, 1, 2, 4096) == 32  # never more than the grid
    assert cluster_units(40, 41, 2, 41 * 128) == 7  # continuation: whole payload chains


def test_bad_client_and_cli_cluster_options_fail_before_compute(model, tmp_path, capsys):
    with pytest.raises(jaxdea.SweepError, match="client must be a dask.distributed.Client"):
        pm.powermap(model, **_axes(SMALL), **RUN, client="tcp://localhost:8786")
    base = ["powermap", CONFIG, *SMALL, *CLI_RUN, "--out", str(tmp_path / "m.zarr")]
    assert main(base + ["--workers", "0"]) == 2
    assert "--workers must be at least 1, got 0" in capsys.readouterr().err
    assert main(base + ["--workers", "2", "--scheduler", "tcp://127.0.0.1:1"]) == 2
    assert "give one of them" in capsys.readouterr().err
    assert not (tmp_path / "m.zarr.parts").exists()


def test_a_killed_worker_loses_nothing(model, long_ref, client, tmp_path):
    store = tmp_path / "m.zarr"
    parts = Path(str(store) + ".parts")
    out: dict = {}

    def run():
        try:
            out["ds"] = pm.powermap(model, **_axes(LONG), **RUN, client=client, store=store)
        except BaseException as exc:  # noqa: BLE001 - reported by the main thread
            out["error"] = exc

    pids = client.run(os.getpid)
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    done = _wait_parts(parts, 3)
    victim = sorted(pids.values())[0]
    os.kill(victim, signal.SIGKILL)  # a worker process dies mid-map
    thread.join(timeout=300)
    assert not thread.is_alive(), "the map did not finish after a worker was killed"
    assert "error" not in out, out.get("error")
    n_chunks = 164 // 4 + (164 % 4 > 0)
    assert done < n_chunks
    ds = out["ds"]
    assert ds.attrs["chunks_computed"] == n_chunks
    _same_map(ds, long_ref)
    _same_map(open_map(store), long_ref)
    client.wait_for_workers(2, timeout=120)  # the nanny restarted the killed worker
    assert victim not in client.run(os.getpid).values()


def test_a_killed_client_resumes_with_only_the_missing_chunks(long_ref, jax_cache, tmp_path,
                                                              capsys):
    store = tmp_path / "m.zarr"
    parts = Path(str(store) + ".parts")
    cmd = [sys.executable, "-m", "jaxdea.cli", "powermap", CONFIG, *LONG, *CLI_RUN,
           "--workers", "2", "--out", str(store)]
    # the CLI's powermap asks for multi-output fusion unless told no: without it, as this
    # process, so that its chunks are this process's to the last bit
    flags = with_extra_option(os.environ.get("XLA_FLAGS", ""), MULTI_OUTPUT_FUSION, "false")
    env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=jax_cache, PYTHONPATH=str(ROOT / "src"),
               XLA_FLAGS=flags)
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)
    try:
        _wait_parts(parts, 3, proc)
        os.kill(proc.pid, signal.SIGKILL)  # the client (and its local cluster) dies
        proc.wait(timeout=30)
        t0 = time.time()  # its worker processes exit when their parent is gone
        while time.time() - t0 < 20:
            try:
                os.killpg(proc.pid, 0)
            except ProcessLookupError:
                break
            time.sleep(0.1)
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # whatever is left of its session
        except ProcessLookupError:
            pass
        proc.wait(timeout=30)
        proc.stdout.close()
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    names = sorted(parts.glob("chunk_*.npz"))
    n_chunks = 41
    assert 3 <= len(names) < n_chunks and not store.exists()
    damaged = names[0]
    damaged.write_bytes(damaged.read_bytes()[:100])  # and one part is truncated
    capsys.readouterr()
    # resumed by one process (another worker count), without --chunk: the run's chunks kept
    code = main(["powermap", CONFIG, *LONG, "--cycles", "10", "--average", "2",
                 "--no-progress", "--out", str(store), "--resume"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    reused = len(names) - 1
    assert f"chunks: {n_chunks - reused} computed, {reused} reused" in captured.out
    assert f"jaxdea: warning: chunk part {damaged} is unreadable" in captured.err
    assert "Traceback" not in captured.err
    assert not parts.exists()
    _same_map(open_map(store), long_ref)


def _interrupted(model, store: Path, client, monkeypatch) -> list[Path]:
    """All chunks finished, killed before the final store was written: the parts remain."""
    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(pm, "write_store", killed)
        with pytest.raises(KeyboardInterrupt):
            pm.powermap(model, **_axes(SMALL), **RUN, client=client, store=store)
    return sorted(Path(str(store) + ".parts").glob("chunk_*.npz"))


@pytest.mark.parametrize("where", ["local", "cluster"])
def test_damaged_or_foreign_parts_are_recomputed_with_a_warning(model, small_ref, client,
                                                                tmp_path, monkeypatch, where):
    use = client if where == "cluster" else None
    store = tmp_path / "m.nc"
    names = _interrupted(model, store, use, monkeypatch)
    assert len(names) == 8
    truncated, flipped, empty, copied = names[1], names[2], names[3], names[5]
    truncated.write_bytes(truncated.read_bytes()[:-40])
    data = bytearray(flipped.read_bytes())
    data[len(data) // 2] ^= 0x01  # one flipped bit in the middle of the arrays
    flipped.write_bytes(bytes(data))
    empty.write_bytes(b"")
    shutil.copyfile(names[0], copied)  # a valid part, of chunk 0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        # without chunk_cells: the interrupted run's 4-cell chunks are kept
        ds = pm.powermap(model, **_axes(SMALL), cycles=10, average=2, progress=False,
                         client=use, store=store, resume=True)
    messages = [str(w.message) for w in caught if issubclass(w.category, PartWarning)]
    assert len(messages) == 4, messages
    for path, why in [(truncated, "is unreadable"), (flipped, ""), (empty, "is unreadable"),
                      (copied, "holds chunk 0, not chunk 5")]:
        assert any(m.startswith(f"chunk part {path} {why}") for m in messages), (path, messages)
    assert ds.attrs["chunks_computed"] == 4 and ds.attrs["chunks_reused"] == 4
    _same_map(ds, small_ref)
    _same_map(open_map(store), small_ref)


def test_cluster_doc_snippets_compile_and_the_slurm_cluster_builds():
    text = (ROOT / "docs" / "cluster.md").read_text()
    blocks = [b.split("```", 1)[0] for b in text.split("```python\n")[1:]]
    assert len(blocks) == 2 and "SLURMCluster(" in blocks[0]
    for i, block in enumerate(blocks):
        compile(block, f"docs/cluster.md python block {i}", "exec")
    try:
        import dask_jobqueue  # noqa: F401 - optional, not a jaxdea dependency
    except ImportError:
        return  # the snippet parses; building it needs dask-jobqueue (no jobs are submitted)
    scope: dict = {}
    exec(blocks[0], scope)  # builds the cluster object (a scheduler, no SLURM job yet)
    try:
        script = scope["cluster"].job_script()
        assert "--cpus-per-task=32" in script or "-n 1" in script
    finally:
        scope["cluster"].close()


def test_rotary_study_on_the_cluster_equals_one_call(client):
    """rotary_study(client=): the (r_i, d) grid in chunks on the workers gives the one-call
    study's numbers (the chunks vectorise differently: compared to 1e-12, statuses equal)."""
    model = jaxdea.load_config(ROOT / "configs" / "rotary_dcdea.toml")
    ri, d = np.linspace(2e-3, 12e-3, 4), np.linspace(4e-3, 14e-3, 5)  # the Fig-12 ranges
    one = jaxdea.rotary_study(model, ri, d)
    many = jaxdea.rotary_study(model, ri, d, client=client, chunk=3)  # 7 tasks, last padded
    np.testing.assert_array_equal(many.status.values, one.status.values)
    assert (one.status.values == 0).sum() >= 10  # mostly settled cells: the check has teeth
    for k in ("theta_deg", "voltage", "rest_stretch", "min_stiffness_eig"):
        np.testing.assert_allclose(many[k].values, one[k].values, rtol=1e-12, atol=0,
                                   equal_nan=True, err_msg=k)
    with pytest.raises(ValueError, match="chunk must be an integer >= 1"):
        jaxdea.rotary_study(model, ri, d, client=client, chunk=0)


def test_de_population_on_the_cluster_equals_the_local_fit(client):
    """DE(client=): each generation's population as slices on the workers (the objective
    sent once per worker); the same seed gives the same fit as in this process."""
    from functools import partial

    from jaxdea.calibration import DE, FrequencyResponse, calibrate, frequency_response

    model = jaxdea.load_config(ROOT / "configs" / "scdea_ls.toml")
    predict = partial(frequency_response, cycles=6, average=2)
    rows = dict(f=np.array([50.0, 90.0]), mass=np.full(2, 2e-3), damping=np.full(2, 0.1))
    data = FrequencyResponse(**rows, P_out=np.asarray(
        predict(model, FrequencyResponse(**rows, P_out=np.ones(2)))["P_out"]) * 1.1)
    kw = dict(bounds={"dielectric.tau": (1e-3, 4e-3)}, predict=predict, curvature=False,
              seed=1)
    here = calibrate(model, data, ["dielectric.tau"], method=DE(population=6, generations=2),
                     **kw)
    there = calibrate(model, data, ["dielectric.tau"], method=DE(
        population=6, generations=2, client=client, slices=3), **kw)
    assert there.n_evals == here.n_evals == 18
    assert there.params["actuator.membrane.dielectric.tau"] == pytest.approx(
        here.params["actuator.membrane.dielectric.tau"], rel=1e-12)
    assert there.loss == pytest.approx(here.loss, rel=1e-9)


def test_a_cluster_without_workers_is_waited_for_then_refused():
    """``check_client`` waits for a first worker where the scheduler lists none at the moment
    (a nanny restarting one on a busy machine: once, right after an interrupted map, the
    next map on this module's cluster failed at once), counts again, and with none after the
    wait refuses in one line, before any compute."""
    from jaxdea.studies.distributed import check_client

    class Scheduler(distributed.Client):  # the two calls check_client makes, no connection
        def __init__(self, later: int):
            self.later, self.waited = later, None

        def scheduler_info(self, n_workers=-1):
            n = 0 if self.waited is None else self.later
            return {"workers": {f"w{i}": {} for i in range(n)}}

        def wait_for_workers(self, n_workers, timeout=None):
            self.waited = timeout
            if self.later < n_workers:
                raise TimeoutError

        def __del__(self):
            pass

    back = Scheduler(2)
    assert check_client(back, wait=5.0) == 2 and back.waited == 5.0
    with pytest.raises(jaxdea.SweepError,
                       match=r"^the Dask cluster has no worker \(waited 5 s\): start workers"):
        check_client(Scheduler(0), wait=5.0)
