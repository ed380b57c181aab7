"""The install files agree: requirements.txt (ComfyUI Manager, the Comfy registry) lists
pyproject.toml's dependencies less torch, and constraints.txt pins every direct requirement at a
version that pyproject.toml's ranges admit; pyproject.toml's registry metadata follows the Comfy
Registry's specification (docs.comfy.org/registry/specifications)."""

import re
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.specifiers import SpecifierSet
from packaging.utils import canonicalize_name
from packaging.version import Version

tomllib = pytest.importorskip("tomllib")  # Python 3.11+

REPO = Path(__file__).resolve().parents[1]
COMFYUI_PROVIDES = {"torch"}


def _lines(name: str) -> list[str]:
    lines = (line.split("#")[0].strip() for line in (REPO / name).read_text().splitlines())
    return [line for line in lines if line]


def _pyproject() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())


def _project() -> dict:
    return _pyproject()["project"]


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


def test_registry_metadata_follows_the_comfy_registry_specification():
    """The node id, a three-part version, the repository, the publisher, ComfyUI versions that admit the one
    .ci/run tests with, one OS classifier, no accelerator one (the pack runs on the CPU too), and the licence
    as an SPDX id (PEP 639; the registry reads it as the licence's text) with its text in LICENSE."""
    pyproject = _pyproject()
    project, comfy = pyproject["project"], pyproject["tool"]["comfy"]
    name = project["name"]
    assert len(name) < 100 and re.fullmatch(r"[A-Za-z](?:[-_.]?[A-Za-z0-9])*", name) and "comfyui" not in name.lower()
    assert re.fullmatch(r"\d+\.\d+\.\d+", project["version"])
    assert project["urls"]["Repository"].startswith("https://github.com/")
    assert comfy["PublisherId"] and comfy["DisplayName"]
    (tested,) = re.findall(r"ComfyUI-(\d+\.\d+\.\d+)\.tar\.gz", (REPO / ".ci" / "run").read_text())
    assert SpecifierSet(comfy["requires-comfyui"]).contains(tested)
    assert project["classifiers"] == ["Operating System :: OS Independent"]
    assert project["license"] == "Apache-2.0" and project["license-files"] == ["LICENSE"]
    assert (REPO / "LICENSE").read_text().split()[:4] == ["Apache", "License", "Version", "2.0,"]


def test_the_messages_for_a_missing_optional_package_name_the_extras_requirement():
    """A missing Ray or PEFT is named with the requirement of its extra (pip install "ray>=2.30"), which works in
    any Python, ComfyUI's included; "artnvg[cluster]" would send pip to an index where artnvg is not ours."""
    from artnvg_core.cluster import RAY_REQUIREMENT
    from artnvg_core.diffusion.lora import PEFT_REQUIREMENT

    extras = _project()["optional-dependencies"]
    assert extras["cluster"] == [RAY_REQUIREMENT] and extras["lora"] == [PEFT_REQUIREMENT]
