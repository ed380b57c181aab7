"""cluster: which workers --devices asks for, and the message when Ray is missing (no Ray needed); the
order of dispatch's hand-outs on a local Ray cluster (its retries are tested through GroupExecutor and
batch)."""

import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from artnvg_core.cli import main as cli
from artnvg_core.cluster import RayUnavailable, Workers, from_wire, plan_workers, ray_session, to_wire
from child_process import child_env


def test_devices_become_workers_of_one_kind():
    assert plan_workers(None) is None
    assert plan_workers(["cuda:0", "cuda:1"]) == Workers("cuda", 2)
    assert plan_workers([torch.device("cpu")] * 3) == Workers("cpu", 3)
    assert Workers("cuda", 2).actor_options()["num_gpus"] == 1 and Workers("cpu", 1).actor_options()["num_gpus"] == 0
    assert Workers("cuda", 1).device() == torch.device("cuda", 0) and Workers("cpu", 1).device().type == "cpu"


@pytest.mark.parametrize("devices, message", [
    (["cuda:0", "cpu"], "expected CUDA devices such as cuda:0,cuda:1 .* got cuda:0,cpu"),
    (["meta"], "got meta"),
    ([], "got none"),
    (["cuda:1", "cuda:1"], "a GPU appears twice in cuda:1,cuda:1"),
])
def test_bad_devices_are_refused(devices, message):
    with pytest.raises(ValueError, match=f"--devices: .*{message}"):
        plan_workers(devices)


@pytest.mark.parametrize("visible, message", [(0, "0 CUDA devices"), (1, "1 CUDA device")])
def test_more_gpus_than_visible_are_refused_counting_those_seen(monkeypatch, visible, message):
    """Once '1 CUDA devices are visible'."""
    monkeypatch.setitem(sys.modules, "ray", type(sys)("ray"))
    sys.modules["ray"].is_initialized = lambda: False
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: visible)
    with pytest.raises(ValueError, match=rf"^--devices: cuda:1 asked for, but this process sees {message}$"):
        with ray_session(["cuda:0", "cuda:1"]):
            pass


def test_without_ray_the_options_that_need_it_say_how_to_install_it(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    with pytest.raises(RayUnavailable, match=r'batch needs Ray, which is not installed: pip install "ray>=2\.30" in the Python that runs ArtNVG'):
        with ray_session(needed_by="batch"):
            pass
    (tmp_path / "jobs.json").write_text('[{"scene": "a.ply", "out": "a.ply"}]')
    assert cli.main(["batch", str(tmp_path / "jobs.json")]) == 2
    assert "error: batch needs Ray, which is not installed" in capsys.readouterr().err


class _Kept(logging.Handler):
    def __init__(self):
        super().__init__()
        self.messages = []

    def emit(self, record):
        self.messages.append(record.getMessage())


def test_rays_token_notice_is_dropped_as_ray_starts_and_its_other_records_kept(monkeypatch):
    """``artnvg batch`` printed Ray's 'Token authentication is enabled for this Ray cluster ...' to the terminal:
    dropped while Ray starts, exactly; a warning or error of Ray's, and the notice outside that call, are logged."""
    notice = ("Token authentication is enabled for this Ray cluster. Set RAY_AUTH_MODE=disabled to opt out. For more "
              "information, see https://docs.ray.io/en/latest/ray-security/token-auth.html")
    logger = logging.getLogger("ray._private.authentication.authentication_token_setup")  # Ray 2.60's
    kept = _Kept()
    logger.addHandler(kept)
    ray = type(sys)("ray")
    ray.is_initialized = lambda: False
    ray.init = lambda **options: [logger.warning(notice), logger.error("the token file is unreadable")]
    ray.shutdown = lambda: None
    monkeypatch.setitem(sys.modules, "ray", ray)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)
    try:
        with ray_session(None, needed_by="batch") as workers:
            assert workers == Workers("cpu", 1)
        logger.warning(notice)
    finally:
        logger.removeHandler(kept)
    assert kept.messages == ["the token file is unreadable", notice]


def test_devices_start_a_new_local_ray_even_where_a_cluster_runs_and_only_an_address_joins_one(monkeypatch):
    """With RAY_ADDRESS set (or after ``ray start --head`` here), a bare ``ray.init(num_cpus=...)`` joins that
    cluster and refuses the resources ('When connecting to an existing cluster, num_cpus and num_gpus must not be
    provided'): ``--devices`` asks for a new local instance (``address="local"``, which Ray starts whatever
    RAY_ADDRESS says); ``--ray-address auto`` joins the cluster RAY_ADDRESS names (Ray reads it for "auto")."""
    calls = []
    ray = type(sys)("ray")
    ray.is_initialized = lambda: False
    ray.init = lambda **options: calls.append({k: options.get(k) for k in ("address", "num_cpus", "num_gpus")})
    ray.shutdown = lambda: None
    monkeypatch.setitem(sys.modules, "ray", ray)
    monkeypatch.setenv("RAY_ADDRESS", "10.0.0.1:6379")
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    for devices in (["cpu", "cpu"], ["cuda:0", "cuda:1"]):
        with ray_session(devices):
            pass
    with ray_session(["cpu"], "auto"):
        pass
    assert calls == [dict(address="local", num_cpus=2, num_gpus=0), dict(address="local", num_cpus=None, num_gpus=2),
                     dict(address="auto", num_cpus=None, num_gpus=None)]


@pytest.mark.slow
def test_a_local_ray_starts_without_printing_its_notices_beside_a_cluster_that_ray_start_left(tmp_path):
    """The real thing, in a child process as the command line runs it (RAY_AUTH_MODE unset, as a user's shell has
    it: set, Ray says nothing), on a machine where ``ray start --head`` wrote its cluster's address for later
    ``ray.init()`` calls to join (here in a Ray temporary folder of the test's own, naming a cluster that is gone)."""
    temporary = Path(tempfile.mkdtemp(prefix="ray", dir="/tmp"))  # short: Ray's socket paths lie under it
    try:
        (temporary / "ray").mkdir()
        (temporary / "ray" / "ray_current_cluster").write_text("127.0.0.1:1")
        script = ("import ray\nfrom artnvg_core.cluster import ray_session\nwith ray_session(['cpu', 'cpu']):\n"
                  "    print('inside', ray.cluster_resources()['CPU'])\n")
        env = {name: value for name, value in child_env().items() if name not in ("RAY_AUTH_MODE", "RAY_ADDRESS")}
        result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                                env=dict(env, RAY_TMPDIR=str(temporary)))
    finally:
        shutil.rmtree(temporary, ignore_errors=True)
    assert result.returncode == 0 and result.stdout == "inside 2.0\n", result
    assert "Token authentication" not in result.stderr and "WARNING" not in result.stderr, result.stderr


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16, torch.uint8, torch.bfloat16])
def test_tensors_cross_ray_as_numpy_arrays_in_shared_memory_and_come_back_the_same(ray_local, dtype):
    tensor = (torch.randn(8, 128, 128, 3, dtype=torch.float64) * 100).to(dtype)[:, ::2]  # not contiguous, > 100 KiB:
    # Ray keeps smaller objects in its own process memory
    assert to_wire(None) is None and from_wire(None) is None
    sent = ray_local.get(ray_local.put(to_wire(tensor)))
    if dtype == torch.bfloat16:  # NumPy has no bfloat16: Ray pickles the tensor
        assert isinstance(sent, torch.Tensor)
    else:  # an array, which Ray serializes as out-of-band buffers (a view of its store, mostly read-only)
        assert isinstance(sent, np.ndarray) and sent.dtype == to_wire(tensor).dtype
    received = from_wire(sent)
    assert received.dtype == dtype and received.shape == tensor.shape and torch.equal(received, tensor)
    received += 1  # its own memory, writable
    assert not isinstance(sent, np.ndarray) or not np.shares_memory(received.numpy(), sent)


class Echo:
    """A Ray actor whose tasks return at once (no CPU slot: it fits beside any pool of the session)."""

    def run(self, task: int) -> int:
        return 10 * task

    def ping(self) -> int:
        return os.getpid()


@pytest.mark.parametrize("tasks, per_actor, handed_before_any_ends", [
    (5, 1, [(0, 0), (1, 1)]),
    (5, 2, [(0, 0), (1, 1), (2, 0), (3, 1)]),  # a second task each while a whole round waits
    (3, 2, [(0, 0), (1, 1)]),  # the last round waits for whichever actor frees first
])
def test_dispatch_hands_a_second_task_only_while_a_round_waits(ray_local, tasks, per_actor, handed_before_any_ends):
    from artnvg_core.cluster import dispatch

    actors = [ray_local.remote(num_cpus=0)(Echo).remote() for _ in range(2)]
    events = []
    for task, actor, value, error in dispatch(actors, list(range(tasks)), lambda a, t: a.run.remote(t),
                                              on_start=lambda task, actor: events.append((task, actor)),
                                              per_actor=per_actor):
        assert error is None and value == 10 * task
        events.append(("ended", task))
    first_end = next(i for i, event in enumerate(events) if event[0] == "ended")
    assert events[:first_end] == handed_before_any_ends
    assert sorted(event[1] for event in events if event[0] == "ended") == list(range(tasks))
    assert sorted(event[0] for event in events if event[0] != "ended") == list(range(tasks))
    for actor in actors:
        ray_local.kill(actor)


def test_kept_workers_outlive_their_pool_until_released_and_a_dead_one_is_replaced(ray_local):
    """A kept pool's actors stay after it closes and a later pool of the same class and kind takes the
    same processes; one killed is started anew; release_workers ends them all (and only kept ones)."""
    from ray.exceptions import RayActorError

    from artnvg_core.cluster import WorkerPool, release_workers

    def processes(pool):
        return ray_local.get([actor.ping.remote() for actor in pool.actors])

    try:
        with WorkerPool(Echo, Workers("cpu", 1), keep=True) as pool:
            first = processes(pool)
        with WorkerPool(Echo, Workers("cpu", 1), keep=True) as pool:
            assert processes(pool) == first
            (killed,) = pool.actors
            pool.kill()
        deadline = time.monotonic() + 60  # ray.kill is asynchronous: a call just after it may still be answered
        with pytest.raises(RayActorError):  # gone for good: no restart (a restarted one would answer until then)
            while time.monotonic() < deadline:
                ray_local.get(killed.ping.remote())
                time.sleep(0.05)
        with WorkerPool(Echo, Workers("cpu", 1), keep=True) as pool:
            second = processes(pool)
        assert second != first
        with WorkerPool(Echo, Workers("cpu", 1)) as own:  # not kept: not named, not released
            assert release_workers() == ["Echo-cpu-0"]
            assert processes(own)
    finally:
        release_workers()
    with pytest.raises(ValueError, match="Failed to look up actor"):
        ray_local.get_actor("Echo-cpu-0", namespace="artnvg")
