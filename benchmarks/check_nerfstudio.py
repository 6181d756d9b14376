r"""Does nerfstudio's own parser read our `transforms.json` as the cameras we exported?

    # 1. a tiny synthetic export (our exporter; the project's environment, with jax; from the
    #    repository root: PYTHONPATH=. unless the package is installed)
    PYTHONPATH=. JAX_PLATFORMS=cpu python benchmarks/check_nerfstudio.py --write-synthetic /tmp/ns_check/per_frame
    PYTHONPATH=. JAX_PLATFORMS=cpu python benchmarks/check_nerfstudio.py --write-synthetic /tmp/ns_check/shared \
        --shared-intrinsics
    # 2. the check, in an environment where nerfstudio installs (`pip install nerfstudio`)
    python benchmarks/check_nerfstudio.py /tmp/ns_check/per_frame /tmp/ns_check/shared
    python benchmarks/check_nerfstudio.py recon/        # any `rvggt reconstruct` output folder

Without `--write-synthetic` the arguments are `rvggt reconstruct` output folders; with it,
the one argument is where a synthetic export is written (10 frames of
`rvggt_jax.synthetic.make_scene`, "original" images of different sizes per frame, or the
same size with `--shared-intrinsics`, through `build_reconstruction` and
`export_reconstruction`, the functions `rvggt reconstruct` writes its folder with), and it
is then checked too when nerfstudio imports in that environment. The two need not share an
environment (nerfstudio brings torch, and dependencies that hold numpy below 2; the project
needs jax): this script imports rvggt_jax only to write, nerfstudio only to check.
docs/benchmarks.md has the commands run and the results; docs/history/nerfstudio.md what the install took.

What is checked, against the folder's `cameras.json` (our cameras in the original
images' pixels: 3x4 world-to-camera with OpenCV axes, 3x3 pinhole, width, height), with
`nerfstudio.data.dataparsers.nerfstudio_dataparser.NerfstudioDataParserConfig`:

1. as written: orientation_method="none", center_method="none", auto_scale_poses=False,
   scale_factor=1, eval_mode="all". The parser must return every image (it sorts them by
   file name; they are matched by path), each file existing at the width and height the
   cameras say; fx, fy, cx, cy, width, height per frame; a perspective camera without
   distortion; camera_to_worlds = our camera-to-world with OpenGL camera axes (inverse of
   the extrinsic, camera y and z flipped); masks only if the frames name `mask_path`.
   Then rays: nerfstudio's `Cameras.generate_rays` through pixel centres of each image
   must pass through the world points our camera sees at those pixels (the pixel
   convention: image spans [0, W] x [0, H] in both).
2. as `ns-train splatfacto --data FOLDER` parses it (the parser's defaults and
   load_3D_points=True): train and eval splits together are every image; their poses are
   ours after the parser's own orient/centre/scale (`dataparser_transform`,
   `dataparser_scale`); the initial points are points.ply's (xyz after the same
   transform, colours), read by nerfstudio through open3d.

Prints the largest differences; any mismatch exits non-zero, each listed on stderr.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

# float32 inside nerfstudio: relative tolerances
INTRINSICS_RTOL = 1e-6
POSE_RTOL = 1e-5
RAY_RTOL = 1e-4


class Mismatch(Exception):
    pass


# ---------------------------------------------------------------------------------------
# writing a synthetic export (rvggt_jax; no nerfstudio)
# ---------------------------------------------------------------------------------------


def write_synthetic(out: Path, shared_intrinsics: bool = False, frames: int = 10) -> None:
    """Our exporter on a tiny synthetic scene (10 frames: the parser's default split then
    holds one image out for eval): network input 28 x 42, "original" images
    larger by 1/scale (per frame, or one scale for all), names out of sorted order and one
    with a space (the export renames it for COLMAP)."""
    from PIL import Image

    from rvggt_jax.app.pipeline import build_reconstruction
    from rvggt_jax.io.export import export_reconstruction
    from rvggt_jax.io.images import ImageInfo
    from rvggt_jax.synthetic import make_scene

    h, w = 28, 42
    scene = make_scene(frames=frames, height=h, width=w, seed=3)
    names = [f"view {c}.png" if i == 1 else f"{c}.png" for i, c in enumerate("zmatkbqcydxw"[:frames])]
    scales = [0.5] * frames if shared_intrinsics else [(0.5, 0.25, 1 / 3)[i % 3] for i in range(frames)]
    with tempfile.TemporaryDirectory() as src:
        paths, infos = [], []
        for i, (name, s) in enumerate(zip(names, scales)):
            ow, oh = round(w / s), round(h / s)
            path = Path(src) / name
            Image.fromarray(scene.images[i]).resize((ow, oh), Image.BILINEAR).save(path)
            paths.append(path)
            infos.append(ImageInfo(path=str(path), name=name, width=ow, height=oh, sx=w / ow, sy=h / oh, ox=0.0,
                                   oy=0.0, valid=(0, 0, w, h)))
        recon = build_reconstruction(scene.images.transpose(0, 3, 1, 2) / 255.0, scene.extrinsics,
                                     scene.intrinsics, scene.depth, np.ones_like(scene.depth), names=names,
                                     infos=infos, conf_threshold="0%")
        export_reconstruction(out, recon, image_paths=paths, write_scene=False)

    # cameras.json (what the check compares against) holds the scene's cameras
    cams = json.loads((out / "cameras.json").read_text())["frames"]
    for i, c in enumerate(cams):
        k = scene.intrinsics[i].copy()
        k[0] *= c["width"] / w
        k[1] *= c["height"] / h
        np.testing.assert_allclose(c["intrinsic"], k, atol=1e-9)
        np.testing.assert_allclose(c["extrinsic"], scene.extrinsics[i], atol=1e-9)
    print(f"wrote {out}: {frames} frames, sizes {[(c['width'], c['height']) for c in cams]}")


# ---------------------------------------------------------------------------------------
# the check (nerfstudio; no rvggt_jax)
# ---------------------------------------------------------------------------------------


def opengl_camera_to_world(extrinsic: np.ndarray) -> np.ndarray:
    """[3, 4] world-to-camera, OpenCV axes -> [4, 4] camera-to-world, OpenGL camera axes
    (x right, y up, z back): what nerfstudio's `transform_matrix` is."""
    w2c = np.vstack([np.asarray(extrinsic, np.float64), [0, 0, 0, 1]])
    c2w = np.linalg.inv(w2c)
    c2w[:3, 1:3] *= -1
    return c2w


def read_ply_xyz_rgb(path: Path) -> tuple[np.ndarray, np.ndarray]:
    from plyfile import PlyData  # (a nerfstudio dependency: an independent PLY reader)

    v = PlyData.read(str(path))["vertex"]
    return (np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64),
            np.stack([v["red"], v["green"], v["blue"]], 1).astype(np.int64))


class Report:
    def __init__(self, folder: Path):
        self.folder, self.errors, self.max_diff, self.counts = folder, [], {}, {}

    def close(self, what: str, got, want, tol: float) -> None:
        got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
        if got.shape != want.shape:
            self.errors.append(f"{what}: shape {got.shape}, expected {want.shape}")
            return
        d = float(np.max(np.abs(got - want))) if got.size else 0.0
        key = what.split("[")[0]
        self.max_diff[key] = max(self.max_diff.get(key, 0.0), d)
        if not d <= tol:
            self.errors.append(f"{what}: max |difference| {d:.3g} > {tol:.3g} (got {got.tolist()}, "
                               f"expected {want.tolist()})")

    def true(self, what: str, ok: bool) -> None:
        if not ok:
            self.errors.append(what)


def load_expected(folder: Path):
    """Our cameras (cameras.json), keyed by the image path that transforms.json gives
    each (frame i of transforms.json is image i of cameras.json: both are written from
    the reconstruction's images in order)."""
    cams = json.loads((folder / "cameras.json").read_text())["frames"]
    tj = json.loads((folder / "transforms.json").read_text())
    if len(tj["frames"]) != len(cams):
        raise Mismatch(f"{folder}: transforms.json has {len(tj['frames'])} frames, cameras.json {len(cams)}")
    return {(folder / f["file_path"]).resolve(): c for f, c in zip(tj["frames"], cams)}, tj


def check_as_written(folder: Path, rep: Report) -> None:
    import torch
    from PIL import Image

    from nerfstudio.cameras.cameras import CameraType
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    expected, tj = load_expected(folder)
    config = NerfstudioDataParserConfig(data=folder, orientation_method="none", center_method="none",
                                        auto_scale_poses=False, scale_factor=1.0, eval_mode="all")
    out = config.setup().get_dataparser_outputs(split="train")
    cams = out.cameras
    files = [Path(p).resolve() for p in out.image_filenames]
    rep.counts["images"] = len(files)
    rep.true(f"{len(files)} images parsed, {len(expected)} exported", len(files) == len(expected))
    rep.true(f"images parsed {sorted(map(str, files))} != exported {sorted(map(str, expected))}",
             set(files) == set(expected))
    rep.close("dataparser_scale", out.dataparser_scale, 1.0, 0)
    rep.close("dataparser_transform", out.dataparser_transform, np.eye(4)[:3], 0)
    rep.true(f"camera type {cams.camera_type.flatten().tolist()} is not perspective",
             bool((cams.camera_type == CameraType.PERSPECTIVE.value).all()))
    rep.close("distortion_params", cams.distortion_params, np.zeros((len(files), 6)), 0)
    # masks: nerfstudio reads them when every frame has mask_path (0 = ignore the pixel)
    mask_paths = [f.get("mask_path") for f in tj["frames"]]
    if any(mask_paths):
        masks = [Path(p) for p in out.mask_filenames or []]
        rep.true(f"{len(masks)} masks parsed for {len(files)} images", len(masks) == len(files))
    else:
        rep.true(f"masks parsed ({out.mask_filenames}) though no frame has mask_path", out.mask_filenames is None)
        masks = [None] * len(files)

    for j, path in enumerate(files):
        c = expected.get(path)
        if c is None:
            continue
        name = path.name
        k, ext, wh = np.array(c["intrinsic"]), np.array(c["extrinsic"]), (c["width"], c["height"])
        rep.true(f"{name}: image file missing", path.is_file())
        if path.is_file():
            with Image.open(path) as im:
                rep.true(f"{name}: image is {im.size[0]}x{im.size[1]}, cameras say {wh[0]}x{wh[1]}", im.size == wh)
        if masks[j] is not None:
            rep.true(f"{name}: mask {masks[j]} missing", masks[j].is_file())
            if masks[j].is_file():
                with Image.open(masks[j]) as im:
                    rep.true(f"{name}: mask is {im.size}, image {wh}", im.size == wh)
        for what, got, want in [("fx", cams.fx[j], k[0, 0]), ("fy", cams.fy[j], k[1, 1]), ("cx", cams.cx[j], k[0, 2]),
                                ("cy", cams.cy[j], k[1, 2])]:
            rep.close(f"{what}[{name}]", got.item(), want, INTRINSICS_RTOL * max(1.0, abs(want)))
        rep.close(f"width_height[{name}]", [cams.width[j].item(), cams.height[j].item()], wh, 0)
        c2w = opengl_camera_to_world(ext)
        scale = max(1.0, float(np.abs(c2w[:3, 3]).max()))
        rep.close(f"camera_to_world[{name}]", cams.camera_to_worlds[j].numpy(), c2w[:3], POSE_RTOL * scale)

        # rays through pixel centres (corners, middle): the points our camera sees there
        wd, ht = wh
        xy = np.array([[0.5, 0.5], [wd - 0.5, 0.5], [0.5, ht - 0.5], [wd - 0.5, ht - 0.5], [wd / 2, ht / 2]])
        rays = cams.generate_rays(camera_indices=torch.full((len(xy), 1), j, dtype=torch.long),
                                  coords=torch.tensor(xy[:, ::-1].copy(), dtype=torch.float32))  # (y, x)
        o, d = rays.origins.double().numpy(), rays.directions.double().numpy()
        cam_dirs = np.linalg.solve(k, np.c_[xy, np.ones(len(xy))].T).T  # OpenCV camera frame, z = 1
        world = (cam_dirs * 2.0 - ext[:, 3]) @ ext[:, :3]  # depth 2 in front of our camera
        rel = world - o
        along = np.sum(rel * d, axis=1)
        off_ray = np.linalg.norm(rel - along[:, None] * d, axis=1)
        rep.true(f"{name}: the points lie behind nerfstudio's rays (along = {along.tolist()})", bool((along > 0).all()))
        rep.close(f"ray_distance[{name}]", off_ray, np.zeros(len(xy)), RAY_RTOL * scale)


def check_as_splatfacto(folder: Path, rep: Report) -> None:
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    expected, tj = load_expected(folder)
    parser = NerfstudioDataParserConfig(data=folder, load_3D_points=True).setup()  # splatfacto's
    seen, train = [], None
    for split in ("train", "val"):
        if split == "val" and len(seen) == len(expected):
            break  # (under 10 images the default 0.9 fraction trains on all, evaluates none)
        out = parser.get_dataparser_outputs(split=split)
        train = out if train is None else train
        rep.counts[split] = len(out.image_filenames)
        t = out.dataparser_transform.double().numpy()
        s = float(out.dataparser_scale)
        for j, p in enumerate(out.image_filenames):
            path = Path(p).resolve()
            seen.append(path)
            c = expected.get(path)
            if c is None:
                continue
            c2w = np.vstack([t, [0, 0, 0, 1]]) @ opengl_camera_to_world(np.array(c["extrinsic"]))
            c2w[:3, 3] *= s
            rep.close(f"splatfacto_camera_to_world[{path.name}]", out.cameras.camera_to_worlds[j].numpy(), c2w[:3],
                      POSE_RTOL * max(1.0, float(np.abs(c2w[:3, 3]).max())))
    rep.true(f"train + val splits hold {sorted(map(str, seen))}, exported {sorted(map(str, expected))}",
             sorted(seen) == sorted(expected))

    # splatfacto's initial points: points.ply in the parser's frame
    if "ply_file_path" not in tj:
        rep.true("transforms.json names no ply_file_path", False)
        return
    xyz, rgb = read_ply_xyz_rgb(folder / tj["ply_file_path"])
    t, s = train.dataparser_transform.double().numpy(), float(train.dataparser_scale)
    pts = train.metadata.get("points3D_xyz")
    if pts is None:
        rep.true("nerfstudio loaded no points3D_xyz from ply_file_path", False)
        return
    want = s * (xyz @ t[:, :3].T + t[:, 3])
    rep.counts["points"] = len(pts)
    rep.close("splatfacto_points3D_xyz", pts.double().numpy(), want,
              POSE_RTOL * max(1.0, float(np.abs(want).max())))
    # (nerfstudio's colours: open3d's float colours * 255, truncated to uint8: off by one at most)
    rep.close("splatfacto_points3D_rgb", train.metadata["points3D_rgb"].numpy(), rgb, 1)


def check_folder(folder: Path) -> Report:
    rep = Report(folder)
    try:
        check_as_written(folder, rep)
        check_as_splatfacto(folder, rep)
    except Mismatch as e:
        rep.errors.append(str(e))
    except Exception as e:  # nerfstudio's parser refusing the folder is a mismatch too
        rep.errors.append(f"nerfstudio could not parse {folder}: {type(e).__name__}: {e}")
    return rep


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folders", nargs="+", type=Path, help="rvggt reconstruct output folders")
    ap.add_argument("--write-synthetic", action="store_true",
                    help="write a synthetic export into the (one) folder first, then check it if nerfstudio imports")
    ap.add_argument("--shared-intrinsics", action="store_true",
                    help="with --write-synthetic: every image the same size (intrinsics at transforms.json's top)")
    args = ap.parse_args(argv)
    if args.write_synthetic:
        if len(args.folders) != 1:
            ap.error("--write-synthetic takes one folder")
        write_synthetic(args.folders[0], args.shared_intrinsics)
        try:
            import nerfstudio  # noqa: F401
        except ImportError:
            print(f"nerfstudio does not import here: check with nerfstudio's python:\n"
                  f"  python {sys.argv[0]} {args.folders[0]}")
            return 0

    import importlib.metadata

    # (torch warns about an indexing form nerfstudio 1.1.5 uses, on every generate_rays)
    warnings.filterwarnings("ignore", message="Using a non-tuple sequence for multidimensional indexing")

    print(f"nerfstudio {importlib.metadata.version('nerfstudio')}, torch {importlib.metadata.version('torch')}")
    failed = 0
    for folder in args.folders:
        rep = check_folder(folder)
        diffs = ", ".join(f"{k} {v:.3g}" for k, v in rep.max_diff.items())
        counts = ", ".join(f"{k} {v}" for k, v in rep.counts.items())
        print(f"{folder}: {counts}; max |difference|: {diffs}")
        if rep.errors:
            failed += 1
            print(f"{folder}: {len(rep.errors)} MISMATCHES", file=sys.stderr)
            for e in rep.errors:
                print(f"  {e}", file=sys.stderr)
        else:
            print(f"{folder}: OK: nerfstudio's parser returns our cameras")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
