"""The npm tools the exchange tests run, pinned in tests/npm/package.json: PlayCanvas splat-transform and
spz-js. On first use they are installed into tests/npm/node_modules (git-ignored) by ``npm install``, which
needs npm and its registry (CI has both); where either is missing the tests that use them are skipped."""

import functools
import json
import shutil
import subprocess
from pathlib import Path

FOLDER = Path(__file__).resolve().parent / "npm"
PINNED = json.loads((FOLDER / "package.json").read_text())["dependencies"]


def _installed() -> bool:
    for name, version in PINNED.items():
        manifest = FOLDER / "node_modules" / name / "package.json"
        if not manifest.is_file() or json.loads(manifest.read_text())["version"] != version:
            return False
    return True


@functools.cache
def unavailable() -> str | None:
    """Why the pinned tools cannot run here, or None once they are installed."""
    if shutil.which("node") is None:
        return "node is not installed"
    if _installed():
        return None
    if shutil.which("npm") is None:
        return "npm is not installed"
    try:
        subprocess.run(["npm", "install", "--no-package-lock", "--no-audit", "--no-fund", "--fetch-retries=0"],
                       cwd=FOLDER, check=True, capture_output=True, text=True, timeout=300)
    except subprocess.CalledProcessError as error:
        return f"npm install in {FOLDER} failed: {error.stderr.strip().splitlines()[-1:]}"
    except subprocess.TimeoutExpired:
        return f"npm install in {FOLDER} took over 300 s"
    return None if _installed() else f"npm install in {FOLDER} did not install {PINNED}"


def splat_transform(source: Path, target: Path) -> None:
    """Convert ``source`` to ``target`` (formats by extension) with splat-transform's default settings."""
    _run([str(FOLDER / "node_modules" / ".bin" / "splat-transform"), "-q", "-w", str(source), str(target)])


def spz_js(source: Path, target: Path) -> None:
    """Convert between .ply and .spz with spz-js, as its README does (tests/npm/spz_js.mjs)."""
    _run(["node", str(FOLDER / "spz_js.mjs"), str(source), str(target)])


def _run(command: list[str]) -> None:
    result = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, f"{command} failed:\n{result.stderr}"
