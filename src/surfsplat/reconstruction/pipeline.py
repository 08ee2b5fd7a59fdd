"""`reconstruct`: photos, a folder or a video -> cameras -> network passes -> one fused scene.

    scene = reconstruct(["a.jpg", "b.jpg"])                       # cameras estimated, the shipped model
    scene = reconstruct("capture.mp4", checkpoint="tiny-synthetic")
    scene = reconstruct("photos/", cameras="photos/cameras.json", size=(256, 256))
    scene = reconstruct("capture/")        # photos + transforms.json or sparse/0: its photos and cameras

Steps:
1. inputs and options are checked (`_check_options`, `read_capture`); a video becomes its chosen
   frames (`surfsplat.capture.select_video_frames`).
2. cameras: given (a camera file, a scene folder, a CameraSet or Cameras, or with cameras="auto" those
   of a processed capture given as `images`: `capture_folder`), or estimated from the
   views (`surfsplat.poses.estimate_cameras`; every pair of up to 30 views is matched, photos or a
   video's chosen frames, and each view with the views 1, 2, 4, ... ahead above that).
3. the network: every `holdout_every`-th view is kept out (to look at the scene from there); the
   others are split into context sets (`surfsplat.capture.context_sets`), one forward pass each,
   with the photos read and resized for that pass only. Where the optimizer runs, its start is
   decided first from the context photos (`surfsplat.capture.starts.choose_start`): a start of
   COLMAP's points ("points", and "auto" where COLMAP finds enough) needs no network, so the model
   is not loaded and steps 3 and 4 do not run (`Scene.network` says so).
4. fusion: one pass is the scene as the model made it (one surfel per pixel); several are fused
   into one scene as they stream by (`surfsplat.capture.SurfelFusion`), optionally each compacted
   first (`compact`), so memory holds the fused surfels and one pass.
5. the fused scene fitted to the context photos: the refinement (colours, opacities, sizes), or
   with `CaptureOptions.optimize` every surfel attribute (`optimize_scene`); held-out views are
   never fitted, and are scored before and after.

Device: the surfels stay where the network made them. Fusion, compaction, the refinement or the
optimization, the held-out scores and the returned Scene (its renders, closure figures and `save`)
all run on the `device` chosen here; the photos are read on the host and sent there once per pass.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import torch

from ..capture import (
    FrameConfig,
    FusionConfig,
    OptimizeConfig,
    RefineConfig,
    SurfelFusion,
    context_sets,
    refine_on_views,
)
from ..geometry.cameras import Cameras
from ..utils.checks import SurfSplatInputError
from .inputs import CaptureInput, ImageSource, read_capture
from .scene import HeldOut, Scene

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class CaptureOptions:
    """How a capture of many views becomes one scene."""

    views_per_pass: int = 3  # context views of one forward pass (3 measured better and faster than 2 on rooms)
    holdout_every: int | None = None  # views 0, k, 2k, ... are kept out of the passes and rendered (None: none)
    matching: Literal["auto", "exhaustive", "sequential"] = "auto"  # pose estimation's image pairs
    frames: FrameConfig = field(default_factory=FrameConfig)  # frame choice of a video
    fusion: FusionConfig = field(default_factory=FusionConfig)  # duplicate removal between views and passes
    # the fused scene's colours, opacities and sizes fitted to the context views (passes > 1 only)
    refine: RefineConfig = field(default_factory=RefineConfig)
    # every surfel attribute fitted to the context views (any number of passes); it replaces the refinement
    optimize: OptimizeConfig = field(default_factory=OptimizeConfig)


def reconstruct(
    images: ImageSource | Sequence[ImageSource],
    checkpoint="tiny-synthetic",
    cameras="auto",
    device: str | torch.device = "auto",
    *,
    size: tuple[int, int] | None = None,
    near: float | None = None,
    far: float | None = None,
    preset: str | None = None,
    trust_pickle: bool = False,
    images_folder: str | None = None,
    focal: float | None = None,
    camera_model: str = "auto",
    max_size: int = 1600,
    max_working_size: int | None = 512,
    compact: int | None = None,
    capture: CaptureOptions | None = None,
    progress: bool = True,
    precision: str = "auto",
    compile: bool = False,
) -> Scene:
    """One scene of surfels from photos, a folder of photos, or a video.

    images:     two or more image files or arrays ([H, W, 3] uint8 or float in [0, 1], or [3, H, W]
                tensors); a folder of images; a processed capture folder (photos and a transforms.json or
                a COLMAP sparse/0: its views are the photos the camera file lists); or a video file (.mp4,
                .mov, ...). Photos are read as displayed (EXIF orientation) and may differ in size and
                orientation: each keeps its own K, and is cropped to the working size (a warning names
                views that lose much of their frame)
    checkpoint: a weights name (default "tiny-synthetic"), hf://owner/repo/file, a checkpoint path,
                or a loaded SurfSplat model
    cameras:    "auto" (default: a processed capture folder's own cameras, else estimated), None
                (estimated from the images), a JSON camera file / COLMAP model / scene folder
                (views matched by name; video frames are named frame_000012, ...), a CameraSet
                (matched by name; arrays take its names in order), or Cameras with K in pixels of
                each view's own image (one per view, in order)
    device:     "auto" (CUDA when available), "cpu", "cuda" or a torch.device
    size:       network input (height, width), multiples of the model's (default: the largest crop of
                the views, downscaled first so that their long side is at most `max_working_size`)
    max_working_size: the default working size's long side in pixels (None: the views' own size);
                a 1080p video's frames (960 px after frame selection) then run at 288x512, not
                528x960: 3.4x fewer pixels and surfels for every later stage
    near, far:  depth range (default: from the cameras, else 0.5 and 100)
    preset, trust_pickle: how to read a release .ckpt given by path
    images_folder: image folder of a scene folder given as `cameras` (e.g. images_4)
    focal, camera_model, max_size: pose estimation (focal length in pixels; lens model fitted, PoseConfig's
                camera_model; long side above which photos are downscaled)
    compact:    a compaction level applied to each pass's surfels before fusion (None: none)
    capture:    CaptureOptions for many views and videos
    precision:  forward passes in "fp32", "bf16" (autocast) or "auto" (bf16 where the device has fast
                bf16); surfels and rendering stay float32
    compile:    the encoder through torch.compile; its compilation (minutes on two cores, timed as the
                stage "compile") pays where one process reconstructs many captures of one size
    Returns a Scene. Bad input raises SurfSplatInputError (or FileNotFoundError) naming it.
    """
    start = time.perf_counter()
    # ---- every input is checked here, before anything heavy runs
    capture = capture or CaptureOptions()
    device = _check_options(capture, device, size, near, far, compact, max_size, max_working_size)
    from ..utils.precision import parse_precision

    parse_precision(precision)
    from .capture_folder import AUTO, capture_views

    if focal is not None and cameras is not None and not (isinstance(cameras, str) and cameras == AUTO):
        raise SurfSplatInputError("--focal: only used when the cameras are estimated (without --cameras)")
    images, cameras, cameras_source = capture_views(images, cameras, images_folder)
    if focal is not None and cameras is not None:  # "auto" found a processed capture's own cameras
        raise SurfSplatInputError(
            f"--focal: only used when the cameras are estimated; {cameras_source} are used "
            "(pass cameras=None to estimate them)"
        )
    views = read_capture(images, capture.frames)
    given = _given_cameras(cameras, views, images_folder if cameras_source is None else None)
    if cameras_source is not None:  # a processed capture's own cameras (a CameraSet read already): named by its file
        given = given[0], cameras_source

    # ---- cameras
    seconds: dict[str, float] = {}
    poses, pose_cameras, photos = None, None, []
    if given is None:
        from ..poses import PoseConfig, estimate_cameras

        # "auto" matches every pair up to 30 views, a video's chosen frames too: on a 3-second clip of 7
        # DTU views the sequential pairs (1, 2, 4 ahead) registered 4 frames and every pair all 7
        config = PoseConfig(
            focal=focal, camera_model=camera_model, max_size=max_size, near=near, far=far, matching=capture.matching
        )
        photos = views.pose_inputs()
        pose_cameras, poses = estimate_cameras(photos, config=config, names=views.names)
        views = views.subset([views.names.index(n) for n in pose_cameras.names])
        given, source = pose_cameras, "estimated from the images (poses.json)"
        seconds["poses"] = poses.seconds
    else:
        given, source = given
    from .sizes import crop_report, view_cameras

    if given.lenses is not None:  # every stage after this sees the pinhole photos
        views, K, c2w = _undistorted_views(views, given, source)
    else:
        # each view's K in pixels of its own photo as displayed (photos may differ in size and orientation)
        own = cameras is None or isinstance(cameras, Cameras)  # estimated K: each in its own photo's pixels
        per_view = view_cameras(given, views.sizes, views.orientations, views.names, source, own_pixels=own)
        K, c2w = per_view.K, per_view.c2w
    near, far = _depth_range(near, far, given)

    # ---- held-out views and context sets
    everything = list(range(len(views)))
    k = capture.holdout_every
    held = [i for i in everything if k is not None and i % k == 0]
    context = [i for i in everything if i not in held]
    if len(context) < 2:
        raise SurfSplatInputError(
            f"holdout_every (--holdout-every): {len(views)} views leave {len(context)} context views; 2 are needed"
        )
    ctx_c2w = c2w[context]

    # ---- the model, where the optimizer's start may need its surfels: a start of COLMAP's points
    # ("points", and "auto" where COLMAP finds enough of them) never runs it
    optimizing = capture.optimize.runs_for(len(context))
    may_skip = optimizing and capture.optimize.start.kind in ("points", "auto")
    model = label = None
    if not may_skip:
        model, label = _load_for_inference(checkpoint, preset, trust_pickle, device, compile)
    shape = _working_shape(views, size, max_working_size, _size_multiple(model))
    cropped = crop_report(views.sizes, views.names, shape)
    if cropped is not None:
        logger.warning(cropped)

    def network_views(indices: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        """The photos [V, 3, H, W] at the network's size and their K [V, 3, 3], on the device: the
        photos are read on the host, and every stage after the network runs where it ran."""
        from ..data.transforms import rescale_and_crop

        # one view at a time: each has its own size and K
        pairs = [rescale_and_crop(views.image(i)[None], K[i : i + 1].to(torch.float32), shape)[:2] for i in indices]
        stack, K_net = torch.cat([p[0] for p in pairs]), torch.cat([p[1] for p in pairs])
        return stack.clamp(0, 1).to(device), K_net.to(device)

    # ---- the optimizer's start, decided from the context photos before any pass
    choice, context_images = None, None
    if may_skip:
        from ..capture.starts import choose_start

        tick = time.perf_counter()
        context_images, K_c = network_views(context)
        cameras_c = Cameras(ctx_c2w.to(device, torch.float32), K_c)
        choice = choose_start(capture.optimize.start, context_images, cameras_c)
        seconds["start"] = time.perf_counter() - tick
    skipped = choice is not None and not choice.needs_network
    if skipped:
        built = _without_network(capture.optimize, choice, context_images, cameras_c)
    else:
        if model is None:  # "auto" found too few points: the network's surfels start
            model, label = _load_for_inference(checkpoint, preset, trust_pickle, device, compile)
            resized = _working_shape(views, size, max_working_size, _size_multiple(model))
            context_images = None if resized != shape else context_images
            shape = resized
        built = _network_passes(
            model, label, capture, views, context, ctx_c2w, c2w, shape, network_views, near, far, compact,
            precision, compile, progress, optimizing, seconds, device,
        )  # fmt: skip
    holdout = None
    if held:
        images_h, K_h = network_views(held)
        holdout = HeldOut([views.names[i] for i in held], Cameras(c2w[held].to(device, torch.float32), K_h), images_h)
        files = [views.sources[i] for i in held]
        holdout.sources = [str(f) for f in files] if all(isinstance(f, (str, Path)) for f in files) else []
    scene = Scene(
        gaussians=built.gaussians,
        cameras=built.cameras,
        width=shape[1],
        height=shape[0],
        names=[views.names[i] for i in context],
        near=near,
        far=far,
        mode=built.mode,
        alpha_threshold=built.alpha_threshold,
        model=built.label,
        checkpoint=_checkpoint_name(checkpoint, label),
        sources=[views.sources[i] for i in context],
        cameras_source=source,
        source_size=(views.width, views.height),
        lenses=None if views.lenses is None else dict(zip(views.names, (pair[0] for pair in views.lenses))),
        passes=[[views.names[context[j]] for j in members] for members in built.passes],
        seconds=seconds,
        compact_level=compact if not skipped else None,
        compact_stats=built.compact_stats,
        fusion_stats=built.fusion_stats,
        refine_stats=built.refine_stats,
        poses=poses,
        pose_cameras=pose_cameras,
        photos=photos,
        video=views.video,
        holdout=holdout,
        precision=built.precision,
        scale_multipliers=built.multipliers,
        multiplier_range=model.cfg.adapter.scale_multiplier_range if built.multipliers is not None else None,
        network=NETWORK_SKIPPED if skipped else "ran",
    )
    if optimizing:  # scores the held-out views before and after it
        from .scene_fit import optimize_scene

        images_c = context_images if context_images is not None else network_views(context)[0]
        optimize_scene(scene, images_c, capture.optimize, progress=progress, choice=choice)
    elif holdout is not None:
        scene.score_holdout()
    seconds["total"] = time.perf_counter() - start
    return scene


# ----------------------------------------------------------------------------------------- stages
NETWORK_SKIPPED = "skipped (the optimizer starts from the SfM points)"  # Scene.network where no pass ran
# the working size's multiple where no model is loaded: every preset's `EncoderConfig.size_multiple`, so
# the size is the one the network would have run at
DEFAULT_SIZE_MULTIPLE = 16


@dataclass
class _Built:
    """What the network's passes (or, without them, the optimizer's start) made of the context views."""

    gaussians: object  # Gaussians [N]
    cameras: Cameras  # the context cameras, K in pixels of the working size
    mode: str
    alpha_threshold: float | None
    label: str  # the network's ("" where none ran)
    passes: list[list[int]]  # context indices of each pass (none without the network)
    precision: str  # what the passes ran in ("none" without them)
    multipliers: torch.Tensor | None = None
    compact_stats: dict = field(default_factory=dict)
    fusion_stats: dict = field(default_factory=dict)
    refine_stats: dict = field(default_factory=dict)


def _size_multiple(model) -> int:
    return model.cfg.encoder.size_multiple if model is not None else DEFAULT_SIZE_MULTIPLE


def _working_shape(views: CaptureInput, size, max_working_size: int | None, m: int) -> tuple[int, int]:
    """(height, width) of every later stage: `size` where given, else the views downscaled to a long
    side of `max_working_size` and cropped to multiples of `m`."""
    if size is None and (views.height < m or views.width < m):  # the user gave images, not a size: name them
        raise SurfSplatInputError(
            f"--images: {views.sources[0]} is {views.width}x{views.height} pixels; the network needs at least {m}x{m}"
        )
    if size:
        shape = tuple(size)
    else:
        shrink = min(1.0, max_working_size / max(views.height, views.width)) if max_working_size else 1.0
        h, w = max(m, round(views.height * shrink)), max(m, round(views.width * shrink))
        shape = (h // m * m, w // m * m)
    if shape[0] < m or shape[1] < m or shape[0] % m or shape[1] % m:
        raise SurfSplatInputError(
            f"size (--size): expected multiples of {m} of at least {m}, got {shape[0]}x{shape[1]}"
        )
    return shape


def _load_for_inference(checkpoint, preset, trust_pickle, device, compile):
    from ..model.loading import prepare_for_inference

    model, label = _load(checkpoint, preset, trust_pickle, device)
    prepare_for_inference(model, compile=compile)
    return model, label


def _without_network(config: OptimizeConfig, choice, images: torch.Tensor, cameras: Cameras) -> _Built:
    """The optimizer's start of COLMAP's points as the scene before the fit: no pass, no fusion, no model.
    It renders as the fit from points does (surfels, plain compositing where `alpha_threshold` is "auto")."""
    from ..capture.starts import make_start

    start, _ = make_start(config.start, None, images, cameras, config.sh_degree, choice)
    threshold = None if config.alpha_threshold == "auto" else config.alpha_threshold
    logger.info(f"network: {NETWORK_SKIPPED}; {len(start):,} COLMAP points start the optimizer")
    return _Built(start, cameras, "surfel", threshold, "", [], "none")


def _network_passes(
    model, label, capture, views, context, ctx_c2w, c2w, shape, network_views, near, far, compact,
    precision, compile, progress, optimizing, seconds, device,
) -> _Built:  # fmt: skip
    """The network's forward passes over the context sets, fused as they stream by (and refined where
    the optimizer does not run)."""
    from ..model.decoder import decoder_mode
    from ..model.pretrained import check_resolution
    from ..utils.log import progress as progress_bar
    from ..utils.precision import autocast

    check_resolution(model, *shape)  # named weights know the resolution they were trained at
    mode = decoder_mode(model.cfg.adapter)
    passes = context_sets(ctx_c2w[:, :3, 3], capture.views_per_pass, views.ordered)
    fusion = SurfelFusion(capture.fusion, mode=mode) if len(passes) > 1 else None
    seconds["forward"] = 0.0  # the stages that run: fusion and compaction only where asked for
    if fusion is not None:
        seconds["fusion"] = 0.0
    if compact is not None:
        seconds["compact"] = 0.0
    compact_stats: dict[str, int] = {}
    single, alpha_threshold, ctx_K, multipliers = None, None, [None] * len(context), None
    for members in progress_bar(passes, desc="forward passes", unit="pass", enabled=progress and len(passes) > 1):
        indices = [context[j] for j in members]
        stack, K_net = network_views(indices)
        for j, kk in zip(members, K_net):
            ctx_K[j] = kk
        cams = Cameras(c2w[indices].to(device, torch.float32), K_net)
        if compile and "compile" not in seconds:  # the compilation, timed apart from the passes
            tick = time.perf_counter()
            with torch.inference_mode(), autocast(precision, device):
                model(stack[None], cams, near, far)
            seconds["compile"] = time.perf_counter() - tick
        tick = time.perf_counter()
        with torch.inference_mode(), autocast(precision, device) as ran:
            prediction = model(stack[None], cams, near, far)
        seconds["forward"] += time.perf_counter() - tick
        alpha_threshold = prediction.alpha_threshold
        # copied out of inference mode: the compaction's refit and the refinement differentiate them;
        # they stay on the device, where every later stage runs
        gaussians = prediction.gaussians.select(0).to(torch.float32).clone()
        if model.cfg.adapter.prior == "surface" and compact is None and len(passes) == 1:
            multipliers = prediction.adapter_output.scales_mul[0].to(torch.float32).clone()
        pixels = None
        if compact is not None:
            tick = time.perf_counter()
            gaussians, pixels = _compact(gaussians, cams, shape, compact, mode, alpha_threshold, compact_stats)
            seconds["compact"] += time.perf_counter() - tick
        if fusion is None:
            single = gaussians
            continue
        fusion.alpha_threshold = alpha_threshold
        tick = time.perf_counter()
        fusion.add(gaussians, cams, shape[0], shape[1], pixels)
        seconds["fusion"] += time.perf_counter() - tick
    gaussians = single if fusion is None else fusion.gaussians()
    scene_cameras = Cameras(ctx_c2w.to(device, torch.float32), torch.stack(ctx_K))
    refine_stats: dict[str, float] = {}
    # the optimization frees what the refinement fits and more: where it runs, the refinement does not
    if fusion is not None and capture.refine.steps_for(len(context)) > 0 and not optimizing:
        tick = time.perf_counter()
        images_c, _ = network_views(context)
        gaussians, refine_stats = refine_on_views(
            gaussians,
            scene_cameras,
            images_c,
            shape[1],
            shape[0],
            capture.refine,
            mode=mode,
            alpha_threshold=alpha_threshold,
            progress=progress,
        )
        seconds["refine"] = time.perf_counter() - tick
    logger.info(
        f"{label}: {len(gaussians):,} surfels from {len(context)} views in {len(passes)} "
        f"pass{'es' if len(passes) > 1 else ''} at {shape[1]}x{shape[0]} in {seconds['forward']:.2f} s"
    )
    return _Built(
        gaussians,
        scene_cameras,
        mode,
        alpha_threshold,
        label,
        passes,
        ran,
        multipliers,
        compact_stats,
        dict(fusion.stats) if fusion is not None else {},
        refine_stats,
    )


# ----------------------------------------------------------------------------------------- checks
def _check_options(
    capture: CaptureOptions, device, size, near, far, compact, max_size, max_working_size
) -> torch.device:
    from ..compaction import LEVELS

    if not isinstance(capture, CaptureOptions):
        raise SurfSplatInputError(f"capture: expected CaptureOptions, got {type(capture).__name__}")
    if capture.views_per_pass < 2:
        raise SurfSplatInputError(
            f"views_per_pass (--views-per-pass): the model matches views, expected at least 2, got {capture.views_per_pass}"
        )
    if capture.holdout_every is not None and capture.holdout_every < 2:
        raise SurfSplatInputError(f"holdout_every (--holdout-every): expected at least 2, got {capture.holdout_every}")
    if size is not None and (len(size) != 2 or any(int(s) != s or s < 1 for s in size)):
        raise SurfSplatInputError(f"size (--size): expected (height, width) in pixels, got {size}")
    for name, value in (("near", near), ("far", far)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise SurfSplatInputError(f"{name} (--{name}): expected a positive depth, got {value}")
    if near is not None and far is not None and not near < far:
        raise SurfSplatInputError(f"near/far (--near/--far): expected 0 < near < far, got {near}, {far}")
    if compact is not None and compact not in LEVELS:
        raise SurfSplatInputError(f"compact (--compact): expected a level in {sorted(LEVELS)}, got {compact}")
    if max_size < 64:
        raise SurfSplatInputError(f"max_size (--max-size): expected at least 64 pixels, got {max_size}")
    if max_working_size is not None and (isinstance(max_working_size, bool) or max_working_size < 16):
        raise SurfSplatInputError(f"max_working_size: expected at least 16 pixels or None, got {max_working_size}")
    return resolve_device(device)


def resolve_device(choice: str | torch.device) -> torch.device:
    """The torch device of "auto" (CUDA when available), "cpu", "cuda" / "cuda:N", or a torch.device,
    which is taken as given (every stage after the network runs where the network ran)."""
    if isinstance(choice, torch.device):
        if choice.type == "cuda" and not torch.cuda.is_available():
            raise SurfSplatInputError(f"device: {choice} was asked for and no CUDA device is available")
        return choice
    if not isinstance(choice, str) or (choice not in ("auto", "cpu") and not choice.startswith("cuda")):
        raise SurfSplatInputError(f"device (--device): expected auto, cpu, cuda or a torch.device, got {choice!r}")
    if choice.startswith("cuda") and not torch.cuda.is_available():
        raise SurfSplatInputError("device (--device cuda): no CUDA device is available")
    if choice == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(choice)


def _given_cameras(cameras, views: CaptureInput, images_folder: str | None):
    """(CameraSet of the views in their order, where they came from), or None to estimate them."""
    from ..data.cameras import CameraSet, load_cameras

    if cameras is None:
        if images_folder is not None:
            raise SurfSplatInputError("images_folder (--images-folder): only used with a scene folder as cameras")
        return None
    if isinstance(cameras, (str, os.PathLike)):
        return load_cameras(cameras, images=images_folder).select(views.names, str(cameras)), str(cameras)
    if isinstance(cameras, CameraSet):
        unnamed = views.video is None and all(p is None for p in views.paths)
        if unnamed and len(cameras.names) == len(views) and not set(views.names) <= set(cameras.names):
            views.names = list(cameras.names)  # arrays have no names of their own: the cameras' in order
        return cameras.select(views.names, "cameras"), "given (CameraSet)"
    if isinstance(cameras, Cameras):
        if len(cameras) != len(views):
            raise SurfSplatInputError(f"cameras: expected {len(views)} cameras (one per view), got {len(cameras)}")
        return CameraSet(cameras, views.width, views.height, list(views.names)), "given (Cameras)"
    raise SurfSplatInputError(
        f"cameras: expected None, a camera file or folder, a CameraSet or Cameras, got {type(cameras).__name__}"
    )


def _undistorted_views(views: CaptureInput, given, source: str) -> tuple[CaptureInput, torch.Tensor, torch.Tensor]:
    """The views of cameras with a lens, read undistorted (`CaptureInput.lenses`), their K [V, 3, 3] and
    c2w [V, 4, 4]: each photo is at its lens's calibrated size (or a uniform downscale of it, the lens rescaled
    with it, `Lens.rescaled`, COLMAP's Camera::Rescale) and becomes the pinhole COLMAP's image_undistorter
    chooses; K is that pinhole's, so every stage after this one sees pinhole photos and cameras. Lenses of
    several sizes (portrait and landscape photos, two phones) give pinholes of several sizes: each view keeps
    its own, and the views then go the way of photos of several sizes (`surfsplat.reconstruction.sizes`: each
    rescaled and cropped to the working size on its own, the reference size the most common orientation's).

    A lens of the stored pixels (`Lens.orientation`, or cameras read without their photos,
    `CameraSet.stored_pixels`) meets a photo read as displayed: the lens's size is the photo's stored
    size, the photo is undistorted in its stored frame and turned back (`surfsplat.data.undistort`), and
    its pinhole and pose turn with it (`displayed_camera`)."""
    from ..data.cameras import pinhole_of
    from ..geometry.orientation import displayed_camera, stored_size
    from .inputs import reference_size

    pairs, Ks, c2ws = [], [], []
    for i, (name, lens) in enumerate(zip(views.names, given.lenses, strict=True)):
        size = views.sizes[i] if views.sizes else (views.width, views.height)
        c2w = given.cameras.c2w[i]
        turn = lens.orientation
        if turn == 1 and given.stored_pixels and views.orientations:
            turn = views.orientations[i]
        stored = stored_size(turn, *size)
        if stored != (lens.width, lens.height):
            if stored[0] > lens.width or abs(lens.height * stored[0] / lens.width - stored[1]) > 0.5:
                shown = f"{size[0]}x{size[1]}" + (f" (stored {stored[0]}x{stored[1]})" if turn != 1 else "")
                raise SurfSplatInputError(
                    f"{source}: image {name!r} is {shown} but its {lens.model} lens is calibrated for "
                    f"{lens.width}x{lens.height} (the photos must be that size or a uniform downscale of it)"
                )
            lens = lens.rescaled(*stored)
        if turn != lens.orientation:  # cameras of the stored pixels meet the photo's EXIF turn here
            flat = pinhole_of(lens, f"{source}: {name}")
            _, c2w, _ = displayed_camera(
                flat.intrinsics(c2w.dtype), c2w, flat.width, flat.height, turn, source=f"{source}: {name}"
            )
            lens = lens.turned(turn)
        pinhole = pinhole_of(lens, f"{source}: {name}")
        pairs.append((lens, pinhole))
        Ks.append(pinhole.intrinsics())
        c2ws.append(c2w)
    sizes = [(p.width, p.height) for _, p in pairs]
    width, height = reference_size(sizes)
    undistorted = views.subset(list(range(len(views))))
    undistorted.width, undistorted.height, undistorted.lenses = width, height, pairs
    undistorted.sizes = sizes
    models = sorted({lens.model for lens, _ in pairs if not lens.is_pinhole})
    if models:
        shown = ", ".join(f"{w}x{h}" for w, h in dict.fromkeys(sizes))
        before = ", ".join(f"{w}x{h}" for w, h in dict.fromkeys(views.sizes or [(views.width, views.height)]))
        logger.info(
            f"cameras with a lens ({', '.join(models)}): the photos are undistorted to {shown} pinholes "
            f"as they are read (from {before})"
        )
    return undistorted, torch.stack(Ks).to(given.cameras.K.dtype), torch.stack(c2ws)


def _depth_range(near: float | None, far: float | None, cams) -> tuple[float, float]:
    near = near if near is not None else (cams.near if cams.near is not None else 0.5)
    far = far if far is not None else (cams.far if cams.far is not None else 100.0)
    if not 0 < near < far:
        raise SurfSplatInputError(f"near/far (--near/--far): expected 0 < near < far, got {near}, {far}")
    return float(near), float(far)


# ----------------------------------------------------------------------------------------- steps
def _is_model(checkpoint) -> bool:
    from ..model import SurfSplat

    return isinstance(checkpoint, SurfSplat)


def _checkpoint_name(checkpoint, label: str | None) -> str:
    """The checkpoint as the user named it (a loaded model: its label; loaded or not, see Scene.network)."""
    if checkpoint is None:
        return "tiny-synthetic"  # `_load`'s default
    if _is_model(checkpoint):
        info = getattr(checkpoint, "pretrained_info", None)
        return label or (info.name if info is not None else "SurfSplat model")
    return str(checkpoint)


def _load(checkpoint, preset, trust_pickle, device):
    from ..model.loading import ModelSpec, load_model

    if checkpoint is None:
        checkpoint = "tiny-synthetic"
    if _is_model(checkpoint):
        info = getattr(checkpoint, "pretrained_info", None)
        return checkpoint.to(device).eval(), info.name if info is not None else "SurfSplat model"
    if not isinstance(checkpoint, (str, os.PathLike)):
        raise SurfSplatInputError(
            f"checkpoint (--checkpoint): expected a name, a path or a SurfSplat model, got {type(checkpoint).__name__}"
        )
    return load_model(ModelSpec(str(checkpoint), preset=preset, trust_pickle=trust_pickle), device)


def _compact(gaussians, cams, shape, level, mode, alpha_threshold, totals):
    """One pass's surfels compacted, with the pixel (view, row, column) each now stands at."""
    from ..compaction import compact_surfels

    result = compact_surfels(gaussians, cams, shape[0], shape[1], level, mode=mode, alpha_threshold=alpha_threshold)
    for key, value in result.stats.items():
        totals[key] = totals.get(key, 0) + int(value)
    cells = result.cells
    centre = cells[:, 3] // 2  # a merged block stands at its middle pixel
    pixels = torch.stack((cells[:, 0], cells[:, 1] + centre, cells[:, 2] + centre), -1)
    return result.gaussians, pixels
