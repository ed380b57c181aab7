"""The install files agree: requirements.txt (ComfyUI Manager, the Comfy registry) lists
pyproject.toml's dependencies less torch, and constraints.txt pins every direct requirement at a
version that pyproject.toml's ranges admit."""

from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

tomllib = pytest.importorskip("tomllib")  # Python 3.11+

REPO = Path(__file__).resolve().parents[1]
COMFYUI_PROVIDES = {"torch"}


def _lines(name: str) -> list[str]:
    lines = (line.split("#")[0].strip() for line in (REPO / name).read_text().splitlines())
    return [line for line in lines if line]


def _project() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())["project"]


def test_requirements_txt_is_pyprojects_dependencies_less_torch():
    dependencies = [Requirement(text) for text in _project()["dependencies"]]
    expected = {str(r) for r in dependencies if r.name not in COMFYUI_PROVIDES}
    listed = [str(Requirement(line)) for line in _lines("requirements.txt")]  # one plain requirement a line
    assert len(listed) == len(set(listed)) and set(listed) == expected
    assert COMFYUI_PROVIDES <= {r.name for r in dependencies}


def test_constraints_pin_every_direct_requirement_inside_its_range():
    project = _project()
    direct = [Requirement(text) for text in project["dependencies"] + project["optional-dependencies"]["test"]]
    pins = {}
    for line in _lines("constraints.txt"):
        pin = Requirement(line)
        (specifier,) = pin.specifier
        assert specifier.operator == "==", line
        pins[canonicalize_name(pin.name)] = Version(specifier.version)
    for requirement in direct:
        assert canonicalize_name(requirement.name) in pins, f"constraints.txt does not pin {requirement.name}"
        assert requirement.specifier.contains(pins[canonicalize_name(requirement.name)], prereleases=True), requirement
