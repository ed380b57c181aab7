"""cluster: which workers --devices asks for, and the message when Ray is missing (no Ray needed here;
dispatch's hand-outs and retries are tested through GroupExecutor and batch on a local Ray cluster)."""

import sys

import pytest
import torch

from artnvg_core.cli import main as cli
from artnvg_core.cluster import RayUnavailable, Workers, plan_workers, ray_session


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


def test_without_ray_the_options_that_need_it_say_how_to_install_it(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    with pytest.raises(RayUnavailable, match=r'batch needs Ray, which is not installed: pip install "artnvg\[cluster\]"'):
        with ray_session(needed_by="batch"):
            pass
    (tmp_path / "jobs.json").write_text('[{"scene": "a.ply", "out": "a.ply"}]')
    assert cli.main(["batch", str(tmp_path / "jobs.json")]) == 2
    assert "error: batch needs Ray, which is not installed" in capsys.readouterr().err
