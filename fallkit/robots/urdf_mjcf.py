"""MuJoCo side of the URDF import (`fallkit.robots.urdf`): compile, fuse static links, write the MJCF.

`convert` takes a read URDF to an MJCF file in the cache: MuJoCo's URDF
compiler reads the prepared XML, fallkit's settings and the caller's `edit` are
applied, static links are fused (keeping the bodies fallkit names), and the
MJCF is written with its meshes into a content-addressed folder.
"""

from __future__ import annotations

import hashlib
import shutil
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Callable, Mapping
from pathlib import Path

import mujoco

from fallkit.errors import URDFError
from fallkit.machine import cache_root
from fallkit.robots.urdf_tree import UrdfTree, choose_root, prepare

_FORMAT = 1  # bump when the conversion changes, so cached folders are not reused


def convert(
    tree: UrdfTree,
    root_link: str | None,
    named: dict[str, str],
    armature: Mapping[str, float] | None,
    package_dirs: Mapping[str, str | Path] | None,
    edit: Callable[[mujoco.MjSpec], None] | None,
    cache_dir: str | Path | None,
    name: str | None,
) -> Path:
    """URDF tree -> MJCF file; `named`: bodies to keep -> where they were named (for errors)."""
    path = tree.path
    root = choose_root(tree, root_link)
    prepare(tree, root, {k: Path(v) for k, v in (package_dirs or {}).items()})
    xml = ET.tostring(tree.root, encoding="unicode")
    try:
        spec = mujoco.MjSpec.from_string(xml)
    except Exception as exc:
        raise URDFError(f"{path}: MuJoCo cannot read it: {one_line(exc)}") from None

    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    for joint in spec.joints:  # torque limits live in the JointSpecs
        joint.actfrclimited = mujoco.mjtLimited.mjLIMITED_FALSE
        joint.actfrcrange = [0.0, 0.0]
    for jname, value in (armature or {}).items():
        joint = spec.joint(jname)
        if joint is None:
            raise URDFError(f"{path}: armature: no joint '{jname}' in the URDF")
        joint.armature = float(value)
    if edit is not None:
        edit(spec)

    for body, where in named.items():
        if spec.body(body) is None:
            known = sorted(b.name for b in spec.bodies if b.name != "world")
            raise URDFError(f"{path}: {where}: no link '{body}' in the URDF (links: {', '.join(known)})")
    _fuse_static(spec, path, root, [root, *named])
    return _write(spec, path, name or tree.name, tree.notes, cache_dir)


def _fuse_static(spec: mujoco.MjSpec, path: Path, root: str, keep: list[str]) -> None:
    """Let MuJoCo fuse static links into their parents, keeping the named ones."""
    # The root must move, or it would be fused into the world; bodies referenced by
    # an element are never fused, so each kept body gets a temporary sensor.
    free = spec.body(root).add_freejoint(name="__fallkit_root")
    temps = []
    for i, body in enumerate(dict.fromkeys(keep)):
        sensor = spec.add_sensor(name=f"__fallkit_keep{i}", type=mujoco.mjtSensor.mjSENS_CONTACT)
        sensor.objtype, sensor.objname = mujoco.mjtObj.mjOBJ_BODY, body
        sensor.intprm[0:3] = [2, 3, 1]
        temps.append(sensor)
    try:
        spec.fuse_static()
        spec.compile()  # every error MuJoCo has about the model, now, naming the URDF
    except Exception as exc:
        raise URDFError(f"{path}: MuJoCo cannot compile it: {one_line(exc)}") from None
    for el in [*temps, free]:
        spec.delete(el)


def _write(spec: mujoco.MjSpec, path: Path, name: str, notes: list[str], cache_dir: str | Path | None) -> Path:
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in name)
    parent = cache_root(cache_dir) / "urdf"
    # Everything goes into a temporary folder renamed at the end: concurrent imports
    # never see half a model. Meshes are copied first: to_xml compiles, relative paths.
    try:
        parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(dir=parent, prefix=f".{safe}-"))
    except OSError as exc:
        raise URDFError(f"{path}: cannot write the converted model into {parent}: {exc}; set FALLKIT_CACHE_DIR") from None
    tmp.chmod(0o755)  # mkdtemp makes it private; the cache may be shared
    try:
        digest = hashlib.sha256()
        copies: dict[str, Path] = {}
        for mesh in spec.meshes:
            src = Path(mesh.file)
            rel, k = f"meshes/{src.name}", 1
            while rel in copies and copies[rel] != src:
                rel, k = f"meshes/{src.stem}_{k}{src.suffix}", k + 1
            if rel not in copies:
                copies[rel] = src
                (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(src, tmp / rel)
                digest.update(rel.encode() + (tmp / rel).read_bytes())
            mesh.file = rel
        spec.modelfiledir = str(tmp)
        spec.compiler.fusestatic = False
        header = f"fallkit URDF import (format {_FORMAT}) of {path.name}: the robot only (no floor, free joint, actuators)"
        spec.comment = "\n".join([header, *(f"repaired: {n}" for n in notes)])
        xml = spec.to_xml()
        digest.update(xml.encode())
        out_dir = parent / f"{safe}-{digest.hexdigest()[:12]}"
        target = out_dir / f"{safe}.xml"
        if not target.is_file():
            (tmp / target.name).write_text(xml)
            try:
                tmp.rename(out_dir)
            except OSError:
                if not target.is_file():  # not a lost race with another process: a real failure
                    raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return target


def one_line(exc: Exception) -> str:
    return " ".join(str(exc).split())
