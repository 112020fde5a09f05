"""`slamkit-export`: turn a run's outputs or its map checkpoint into other formats.

`SOURCE` is a run folder (its map.ply, or its checkpoint.zip when it has none: `mapper=none`) or a
map checkpoint file. `slamkit-export ply SOURCE [--out FILE]` writes the map in the 3DGS PLY
layout that splat viewers open. `slamkit-export mesh SOURCE [--voxel 0.01]` renders expected depth
and colour (where the opacity reaches `--min-alpha`, so that half-transparent edges do not smear
the surface) at every keyframe pose (`keyframes.txt`, camera-to-world) with the run's camera and
the `auto` rasteriser, fuses them into open3d's ScalableTSDFVolume (voxel in metres; extra
`mesh`) and writes the marching-cubes mesh (world metres, vertex colours and normals).

Gaussians with a non-finite parameter are left out, with their count. `--out` is never a folder,
a map checkpoint or in the folder of a run still going (docs/checkpoints.md, "Export"). Exit
status: 0; 2 a bad source or --out, one line; 1 the output could not be written, one line.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slamkit.cli import streams
from slamkit.errors import DataError, OutputError, SlamkitError
from slamkit.geometry.registration import import_open3d
from slamkit.types import Camera

#: The TSDF truncation distance is this many voxels unless --sdf-trunc is given.
SDF_TRUNC_VOXELS = 4.0
#: Depth cut-off for fusion (metres) when the run's camera.json has none.
FALLBACK_DEPTH_TRUNC = 10.0


@dataclass
class MeshResult:
    """What `export_mesh` made: the file, its size and the work done (seconds)."""

    path: Path
    num_vertices: int
    num_triangles: int
    num_views: int
    seconds: float
    dropped: int = 0  # Gaussians left out: a non-finite parameter


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}") from None
    if not (value > 0 and np.isfinite(value)):
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return value


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}")
    return value


def _unit_interval(text: str) -> float:
    value = _positive_float(text)
    if value > 1:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1], got {text!r}")
    return value




def read_camera(path: Path) -> tuple[Camera, float | None]:
    """(camera in pixels, depth_trunc in metres or None) from a run's camera.json."""
    if not path.is_file():
        raise DataError(f"{path} not found (runs write it since slamkit-export exists; re-run slamkit)")
    try:
        data = json.loads(path.read_text())
        camera = Camera(int(data["width"]), int(data["height"]), float(data["fx"]), float(data["fy"]),
                        float(data["cx"]), float(data["cy"]))
        depth_trunc = None if data.get("depth_trunc") is None else float(data["depth_trunc"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise DataError(f"{path}: expected JSON with width, height, fx, fy, cx, cy "
                        f"({type(exc).__name__}: {exc})") from None
    if camera.width < 1 or camera.height < 1 or camera.fx <= 0 or camera.fy <= 0:
        raise DataError(f"{path}: expected a positive image size and focal lengths, got {data}")
    return camera, depth_trunc


def read_keyframe_poses(path: Path) -> np.ndarray:
    """(K,4,4) camera-to-world keyframe poses (metres) from a run's keyframes.txt (TUM format)."""
    from slamkit.formats.tum import read_tum_trajectory

    if not path.is_file():
        raise DataError(f"{path} not found (runs write it since slamkit-export exists; re-run slamkit)")
    if not path.read_text().strip():
        raise DataError(f"{path}: no keyframes (the run made none, so there is no view to fuse)")
    _, poses = read_tum_trajectory(path)
    return poses


def check_run_dir(run_dir: Path) -> Path:
    """The run's map.ply; DataError when RUN_DIR or its map is missing."""
    if not run_dir.is_dir():
        raise DataError(f"run directory {run_dir} not found (expected a slamkit run folder)")
    map_ply = run_dir / "map.ply"
    if not map_ply.is_file():
        raise DataError(f"{map_ply} not found: the mesh is made from the Gaussian map; run slamkit with "
                        "mapper=gaussian_splatting")
    return map_ply


def export_mesh(run_dir: Path, out: Path | None = None, voxel: float = 0.01, sdf_trunc: float | None = None,
                depth_trunc: float | None = None, min_alpha: float = 0.5, scale: float = 1.0,
                every: int = 1, rasterizer: str = "auto") -> MeshResult:
    """Fuse renders of RUN_DIR's map.ply at its keyframe poses into a TSDF mesh written to `out`
    (default RUN_DIR/mesh.ply). voxel, sdf_trunc, depth_trunc: metres (sdf_trunc default 4
    voxels; depth_trunc default the run's, else 10 m). scale: render resolution relative to the
    run's camera. every: use every n-th keyframe."""
    from slamkit.formats.ply import load_ply
    from slamkit.registry.discovery import create_rasterizer
    from slamkit.run import checkpoint

    source = Path(run_dir)
    start = time.perf_counter()
    if _is_checkpoint(source):
        gaussian_map, saved = checkpoint.load_map(source)
        camera, run_depth_trunc = Camera(**saved["camera"]), saved.get("depth_trunc")
        poses = checkpoint.keyframe_poses(saved)[::every]
        if not len(poses):
            raise DataError(f"{source}: the checkpoint's run made no keyframe, so there is no view to fuse")
        run_dir = source if source.is_dir() else source.parent
    else:
        map_ply = check_run_dir(source)
        camera, run_depth_trunc = read_camera(source / "camera.json")
        poses = read_keyframe_poses(source / "keyframes.txt")[::every]
        gaussian_map, run_dir = load_ply(map_ply), source
    gaussian_map, dropped = finite_map(gaussian_map)
    o3d = import_open3d()
    out = Path(out) if out is not None else run_dir / "mesh.ply"
    check_out(out)
    depth_trunc = depth_trunc or run_depth_trunc or FALLBACK_DEPTH_TRUNC
    camera = camera if scale == 1.0 else camera.scaled(scale)
    backend = create_rasterizer(rasterizer)
    volume = o3d.pipelines.integration.ScalableTSDFVolume(
        voxel_length=voxel, sdf_trunc=sdf_trunc or SDF_TRUNC_VOXELS * voxel,
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8)
    intrinsic = o3d.camera.PinholeCameraIntrinsic(camera.width, camera.height, camera.fx, camera.fy, camera.cx,
                                                  camera.cy)
    for pose in poses:
        rgbd = _render_rgbd(o3d, backend, gaussian_map, pose, camera, min_alpha, depth_trunc)
        volume.integrate(rgbd, intrinsic, _world_to_camera(pose))
    mesh = volume.extract_triangle_mesh()
    if len(mesh.vertices) == 0:
        raise DataError(f"{source}: no surface to mesh: no rendered pixel reached --min-alpha {min_alpha} (an "
                        "untrained map, mapper=none, is faint: try --min-alpha 0.2)")
    mesh.compute_vertex_normals()
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot write {out}: {exc.strerror or exc}") from None
    if not o3d.io.write_triangle_mesh(str(out), mesh):
        raise OutputError(f"cannot write the mesh to {out} (open3d could not write it there)")
    return MeshResult(out, len(mesh.vertices), len(mesh.triangles), len(poses), time.perf_counter() - start, dropped)


def finite_map(gaussian_map):
    """(`gaussian_map` without its Gaussians that have a non-finite parameter, how many those were)."""
    from slamkit.formats.ply import finite_rows
    from slamkit.map.gaussian_map import GaussianMap

    keep = finite_rows(gaussian_map)
    if keep.all():
        return gaussian_map, 0
    finite = GaussianMap(gaussian_map.device)
    finite.append(gaussian_map.rows().select(keep))
    return finite, int((~keep).sum())


def check_out(out: Path, source: Path | None = None) -> None:
    """DataError unless `out` names a file slamkit-export may write: not a folder, not a map
    checkpoint (nor the `source` read), not in the folder of a run that is still going."""
    from slamkit.formats.checkpoint import CHECKPOINT_NAME, CheckpointError, read_meta
    from slamkit.run.ownership import in_use_by

    if out.is_dir():
        raise DataError(f"--out {out} is a folder (expected a file name, e.g. {out / 'map.ply'})")
    checkpoint = out.name == CHECKPOINT_NAME or (source is not None and out.absolute() == source.absolute())
    if not checkpoint and out.is_file():
        try:
            read_meta(out)
            checkpoint = True
        except CheckpointError:
            pass
    if checkpoint:
        raise DataError(f"--out {out} is a map checkpoint; slamkit-export never writes over one (choose another "
                        "file)")
    holder = in_use_by(out.parent)
    if holder is not None:
        raise DataError(f"--out {out}: its folder belongs to a run that is still going ({holder}); wait for it to "
                        "end, or choose another folder")


def _is_checkpoint(source: Path) -> bool:
    """A checkpoint file, or a run folder without map.ply that has a checkpoint."""
    from slamkit.formats.checkpoint import CHECKPOINT_NAME

    if source.is_dir():
        return not (source / "map.ply").is_file() and (source / CHECKPOINT_NAME).is_file()
    return source.is_file() or source.suffix == ".zip"


def export_ply(source: Path, out: Path | None = None) -> tuple[Path, int, int]:
    """Write a checkpoint's map (SOURCE: the file or its run folder) as a 3DGS PLY (default:
    map.ply beside the checkpoint); returns (the file, the Gaussians written, those left out for
    a non-finite parameter)."""
    from slamkit.formats.checkpoint import checkpoint_path
    from slamkit.formats.ply import save_ply
    from slamkit.run import checkpoint

    path = checkpoint_path(source)
    gaussian_map, _ = checkpoint.load_map(path)
    out = Path(out) if out is not None else path.parent / "map.ply"
    check_out(out, path)
    try:
        dropped = save_ply(out, gaussian_map)
    except OSError as exc:
        raise OutputError(f"cannot write {out}: {exc.strerror or exc}") from None
    return out, len(gaussian_map) - dropped, dropped


def _world_to_camera(pose: np.ndarray) -> np.ndarray:
    from slamkit.geometry.transforms import invert_pose

    return invert_pose(np.asarray(pose, dtype=np.float64))


def _render_rgbd(o3d, backend, gaussian_map, pose: np.ndarray, camera: Camera, min_alpha: float, depth_trunc: float):
    """open3d RGBD image of the map rendered from `pose` (camera-to-world): expected colour
    (uint8) and expected depth (float32 metres, 0 where alpha < min_alpha)."""
    from slamkit.roles.rendering import render_map

    out = render_map(backend, gaussian_map, pose, camera)
    depth = np.ascontiguousarray(out.expected_depth(min_alpha).cpu().numpy().astype(np.float32))
    color = np.ascontiguousarray((out.expected_color(min_alpha).cpu().numpy() * 255 + 0.5).astype(np.uint8))
    return o3d.geometry.RGBDImage.create_from_color_and_depth(
        o3d.geometry.Image(color), o3d.geometry.Image(depth), depth_scale=1.0, depth_trunc=depth_trunc,
        convert_rgb_to_intensity=False)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="slamkit-export", description=__doc__.split("\n")[0])
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    mesh = commands.add_parser("mesh",
                               help="TSDF mesh of a run's Gaussian map (needs open3d: pip install -e '.[mesh]')",
                               description="Fuse renders of RUN_DIR/map.ply at the keyframe poses into a TSDF mesh.")
    mesh.add_argument("run_dir", type=Path, metavar="SOURCE",
                      help="a slamkit run folder (mapper=gaussian_splatting) or its checkpoint.zip")
    mesh.add_argument("--out", type=Path, default=None, help="mesh file (.ply, .obj, ...; default RUN_DIR/mesh.ply)")
    mesh.add_argument("--voxel", type=_positive_float, default=0.01, help="TSDF voxel size in metres (default 0.01)")
    mesh.add_argument("--sdf-trunc", type=_positive_float, default=None,
                      help="TSDF truncation in metres (default 4 voxels)")
    mesh.add_argument("--depth-trunc", type=_positive_float, default=None,
                      help="fuse rendered depth up to this many metres (default: the run's depth_trunc, else 10)")
    mesh.add_argument("--min-alpha", type=_unit_interval, default=0.5,
                      help="fuse only pixels whose rendered opacity reaches this (default 0.5)")
    mesh.add_argument("--scale", type=_unit_interval, default=1.0,
                      help="render resolution relative to the run's camera (default 1)")
    mesh.add_argument("--every", type=_positive_int, default=1, help="use every n-th keyframe (default 1)")
    mesh.add_argument("--rasterizer", default="auto", help="rasteriser backend: auto | cpu | torch | gsplat")
    ply = commands.add_parser("ply", help="a map checkpoint's Gaussians as a 3DGS PLY (splat viewers open it)",
                              description="Write the map of a checkpoint in the 3DGS PLY layout.")
    ply.add_argument("source", type=Path, metavar="SOURCE", help="a run folder with checkpoint.zip, or the file")
    ply.add_argument("--out", type=Path, default=None, help="PLY file (default: map.ply beside the checkpoint)")
    return parser


def _dropped(n: int) -> str:
    return f" (dropped {n} non-finite Gaussian{'s' if n != 1 else ''})" if n else ""


def main(argv: list[str] | None = None) -> int:
    streams.guard()  # a closed, broken or full stdout / stderr never stops the command
    args = _parser().parse_args(argv)
    try:
        if args.command == "ply":
            path, n, dropped = export_ply(args.source, args.out)
            print(f"slamkit-export: {n} Gaussians: {path}{_dropped(dropped)}")
            return 0
        result = export_mesh(args.run_dir, args.out, args.voxel, args.sdf_trunc, args.depth_trunc, args.min_alpha,
                             args.scale, args.every, args.rasterizer)
    except SlamkitError as exc:
        if os.environ.get("SLAMKIT_DEBUG"):
            raise
        print(f"slamkit-export: error: {exc}", file=sys.stderr)
        return exc.exit_status
    print(f"slamkit-export: mesh with {result.num_vertices} vertices, {result.num_triangles} triangles from "
          f"{result.num_views} keyframe views in {result.seconds:.1f} s: {result.path}{_dropped(result.dropped)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
