"""The add-on's files for a Blender installation: a small package ``likeness_blender`` (legacy ``bl_info`` for
Blender 4.2+ add-on folders, and ``blender_manifest.toml`` for installing the zip as an extension) that puts this
project (and, after Blender's own, the Python environment Likeness runs in, for onnxruntime, scipy and pyzmq) on
Blender's module path and registers :mod:`studio.blender.addon`.

The add-on runs the project's code in place, so a ``git pull`` updates it; installing again is needed only when the
project or its environment moves. Blender's Python must be the environment's minor version (3.11 for Blender
4.2–5.0), else the compiled dependencies do not load: the add-on says so when it is enabled.
"""

from __future__ import annotations

import io
import os
import sys
import sysconfig
import zipfile
from pathlib import Path

from models.atomic import write_bytes, write_text
from models.errors import UsageError

ADDON = "likeness_blender"
ROOT = Path(__file__).resolve().parents[2]
VERSION = (0, 1, 0)

_SHIM = '''"""Likeness: a soft animatronic face's predicted skin in Blender (written by `likeness blender install`).

Puts the Likeness project and its Python environment on Blender's module path and registers the add-on that lives
in the project (studio/blender/addon.py).
"""

import sys

bl_info = {{
    "name": "Likeness",
    "author": "Likeness",
    "version": {version},
    "blender": (4, 2, 0),
    "location": "3D Viewport > Sidebar > Likeness",
    "description": "Animate a Likeness head on its predicted skin; export clips; stream to the daemon",
    "category": "Animation",
}}

PROJECT = {project!r}
SITE = {site!r}
PYTHON = {python!r}


def _paths():
    if sys.version_info[:2] != tuple(PYTHON):
        raise RuntimeError(
            "Likeness: Blender runs Python %d.%d but the Likeness environment is Python %d.%d; its compiled "
            "packages (onnxruntime, scipy, pyzmq) cannot load. Install Likeness with Python %d.%d, or install "
            "those packages into Blender's Python." % (*sys.version_info[:2], *PYTHON, *sys.version_info[:2]))
    if PROJECT not in sys.path:
        sys.path.insert(0, PROJECT)
    for site in SITE:
        if site not in sys.path:
            sys.path.append(site)  # after Blender's own packages: Blender's numpy wins


def register():
    _paths()
    from studio.blender import addon

    addon.register()


def unregister():
    from studio.blender import addon

    addon.unregister()
'''

_MANIFEST = '''schema_version = "1.0.0"
id = "{addon}"
version = "{version}"
name = "Likeness"
tagline = "Animate a Likeness head on its predicted skin"
maintainer = "Likeness"
type = "add-on"
blender_version_min = "4.2.0"
license = ["SPDX:MIT"]

[permissions]
network = "Stream poses to a Likeness daemon and send its E-stop"
files = "Read heads, clips and recordings; write clips"
'''


def addon_files(project: Path = ROOT, site: list[str] | None = None) -> dict[str, str]:
    """The add-on package's files (name → text) pointing at ``project`` and the environment's ``site`` folders."""
    if site is None:
        paths = sysconfig.get_paths()
        site = list(dict.fromkeys([paths["purelib"], paths["platlib"]]))
    shim = _SHIM.format(version=VERSION, project=str(project), site=site, python=list(sys.version_info[:2]))
    manifest = _MANIFEST.format(addon=ADDON, version=".".join(map(str, VERSION)))
    return {"__init__.py": shim, "blender_manifest.toml": manifest}


def user_addon_dir(blender_version: str, platform: str = sys.platform, env: dict[str, str] | None = None) -> Path:
    """Blender's user add-on folder for a version (``5.0``) on this platform (Blender's defaults; the
    ``BLENDER_USER_SCRIPTS`` environment variable overrides them, as in Blender)."""
    env = dict(os.environ) if env is None else env
    parts = blender_version.split(".")
    if len(parts) < 2 or not all(p.isdigit() for p in parts[:2]):
        raise UsageError(f"--blender-version must be MAJOR.MINOR such as 4.2 or 5.0 (got {blender_version!r})")
    version = ".".join(parts[:2])
    if env.get("BLENDER_USER_SCRIPTS"):
        return Path(env["BLENDER_USER_SCRIPTS"]) / "addons"
    home = Path(env.get("HOME", str(Path.home())))
    if platform == "darwin":
        base = home / "Library" / "Application Support" / "Blender"
    elif platform.startswith("win"):
        base = Path(env.get("APPDATA", str(home / "AppData" / "Roaming"))) / "Blender Foundation" / "Blender"
    else:
        base = Path(env.get("XDG_CONFIG_HOME") or home / ".config") / "blender"
    return base / version / "scripts" / "addons"


def install(target: str | Path | None = None, blender_version: str = "5.0") -> Path:
    """Write the add-on package into ``target`` (default: Blender's user add-on folder); returns its folder."""
    folder = (Path(target) if target is not None else user_addon_dir(blender_version)) / ADDON
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"cannot create the add-on folder {folder}: {exc.strerror or exc}") from exc
    for name, text in addon_files().items():
        write_text(folder / name, text)
    return folder


def build_zip(out: str | Path) -> Path:
    """The add-on as a zip for Blender's Preferences → Add-ons → Install from Disk."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for name, text in addon_files().items():
            z.writestr(f"{ADDON}/{name}", text)
    return write_bytes(out, buf.getvalue())
