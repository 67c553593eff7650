"""The training settings of ``manisplat-reconstruct``: a plain dataclass, importable without torch
(the command line reads its defaults before deciding whether to load anything)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class TrainConfig:
    """Optimisation settings (defaults used for the measurements in the README).

    Attributes:
        iters: training iterations (one frame each).
        lambda_app, lambda_mask, lambda_pose: loss weights (paper: 1.0 each; the command line
            weighs the mask loss by where the masks come from: :func:`resolve_lambda_mask`). The
            pose prior weighs 0.01: at 1 its gradient outweighs the images' for an object a few
            hundred pixels large, and the poses stay where the pseudo ground truth put them.
        lambda_smooth: weight of the pose corrections' smoothness loss (each moving frame's
            correction against its trained neighbours'; :mod:`manisplat.reconstruct.poses`); the
            command line weighs it by the cameras trained: :func:`resolve_lambda_smooth`.
        ssim_weight: D-SSIM share of the render and appearance losses.
        densify: clone/split/prune (gsplat defaults; refine every ``refine_every`` from
            ``refine_start`` to ``refine_stop_fraction`` of the iterations), each node growing to
            at most ``growth_cap`` times its initial size (unbounded growth on these sharp
            synthetic images multiplied the Gaussians by 6 and the time with them).
        shadows: learn cast shadows of the moving parts (searched at ``shadow_start``).
        shadow_receivers: what they darken: "all" (the background and the moving parts: the
            gripper's shadow on the object, the arm's on itself), "background" (the earlier
            model, whose moving parts bake what shadows they had in the recording into colour) or
            "shaded" ("all", and the objects lit by their surfaces' angle to the light:
            :mod:`manisplat.scene.shadows`).
        light_response: the moving parts' Gaussians learn how their colour follows the
            shadows' light as the part turns under it (``light_gain``,
            :mod:`manisplat.scene.gaussians`): a wrist camera sees its gripper's fingers from one
            direction whatever the arm does, so their view-dependent bands cannot follow the light.
        shadow_casters: what casts the links' shadows: "gaussians" (the links' fitted Gaussians,
            which reach past the surface: wider shadows) or "meshes" (points sampled over the robot
            description's link meshes: the links' outlines; the Gaussians where it has none).
            Meshes: +0.8 dB held-out and +0.4 dB at new poses on the one-arm episode, but 0.3-0.7
            dB less in the object region held out (docs/benchmarks.md), so not yet the default.
        shadow_resolution: the shadow map's size (pixels a side; it spans about twice the
            robot's reach). None: a texel about one camera pixel wide at the robot
            (:func:`manisplat.scene.shadows.matched_resolution`; 368 for the simulator's
            320x240 camera, 96 for the built-in 160x120 sample). A coarse map blurs the
            shadows' edges (at 128 their outlines were the largest errors left on the test
            set); a finer one costs time and adds nothing the camera resolves.
        rasterize_mode: "classic" (gsplat's default: the 0.3 px^2 dilation that keeps splats at
            least a pixel wide adds area at full opacity) or "antialiased" (Mip-Splatting's 2D
            filter, gsplat's mode of that name: a 0.1 px^2 dilation, about a pixel's own area,
            and the opacity scaled so that a splat keeps its integral; Gaussians fitted to a
            wrist camera's close-ups, seen from the head camera a metre away, are then drawn as
            faint and as sharp as they are small). The twin keeps it and its dilation.
        object_position_rate: the objects' Gaussians' position learning rate as a fraction of
            the scene's (1.6e-4 x the scene's scale, about 1.2 m, decaying 100x). At 1 a 4 cm box
            takes a room's steps and half its Gaussians sink 2-5 mm inside its faces; at 0.3 they
            stay within about 1.6 mm and the box is drawn 0.7 dB nearer the simulator's at 50 new
            starts, yet policies trained on that twin's demonstrations did worse (docs/benchmarks.md,
            policies trained on the output), so 1 stays the default.
        pose_rate_final: the object poses' learning rate at the end of training as a fraction of
            its start (exponential in between). At 1 (constant, the rate until 2026-12-04) a twist
            stepped often (an object at rest, one twist for all its frames) wandered a millimetre
            from where the images put it once the Gaussians had stopped moving; at 0.01 (the
            positions' decay, the default until 2026-12-05) the images corrected less of the pseudo
            ground truth late in training: on the Cobot Magic handover the box came out further off
            and the wrist cameras' object regions 1.1-1.7 dB worse than at 0.1 (docs/benchmarks.md).
        fixed_camera_weight: the factor on the gradients a fixed camera's frames give the objects'
            Gaussians (the command line's :func:`resolve_fixed_camera_weight`: above 1 only where
            cameras riding on an arm are trained too). A wrist camera's close-up gives an object's
            Gaussians gradients 17-30 times those of the head camera a metre away, where the
            object covers a few hundred pixels; in one loss the close-ups decided how the object
            looks, and the head camera's view of it was left unfitted (its object region 2.7-3.6 dB
            below the head camera's alone on the Cobot Magic samples; docs/benchmarks.md). The
            poses, the robot, the background and densification's statistics take the gradients
            as they are.
        fixed_camera_share: the probability that an iteration draws a fixed camera's frame where
            cameras riding on an arm are trained too (None: every camera's frames alike, 1/3 for
            the head camera of a Cobot Magic; the command line's ``--fixed-camera-share``,
            :func:`resolve_fixed_camera_share`: 0.5 from 10 000 iterations on). With the wrist
            cameras the head camera gets a third of the iterations and its full image stayed
            under what it draws alone; 0.5 at 10 000 iterations lifts it 0.1-0.4 dB, to 35.3 on
            both Cobot Magic samples, the wrist cameras' 0.2-0.7 dB lower (docs/benchmarks.md).
        sh_degree, sh_every: view-dependent colour bands (evaluated in each node's frame), one
            more band switched on every ``sh_every`` iterations.
        refine_camera: also optimise a correction of the camera extrinsic.
        exposure: a gain per colour channel and frame (auto-exposure, white balance;
            :mod:`manisplat.reconstruct.exposure`), fitted on each training frame's static pixels.
        backend: rasterizer backend ("auto": gsplat on CUDA, the C++ one on the CPU; "cpu",
            "torch", "gsplat").
        device: torch device of training ("cpu", "cuda", "cuda:N", or "auto": CUDA when
            available); resolved by :func:`resolve_device` (a string here: no torch import).
        compile: run the iteration's tensor functions (placement, shadows, loss, densification
            statistics) through ``torch.compile`` ("on", "off"; "auto": on CUDA for long runs;
            :func:`resolve_compile`). The same training with fewer, fused kernels; the first
            iterations pay the compilation.
        eval_every: iterations between held-out PSNR estimates (for the progress bar).
        log_every: iterations between reads of the running loss for the progress bar. The
            training iteration never reads a value back from the device otherwise (no
            host-device synchronisation) except on densification steps (``refine_every``:
            the Gaussians change number) and every ``eval_every`` iterations.
        seed: random seed (frame order, densification samples).
    """

    iters: int = 3000
    lambda_app: float = 1.0
    lambda_mask: float = 1.0
    lambda_pose: float = 0.01
    lambda_smooth: float = 0.0
    ssim_weight: float = 0.2
    densify: bool = True
    refine_start: int = 300
    refine_every: int = 100
    refine_stop_fraction: float = 0.7
    grow_grad2d: float = 0.0002
    growth_cap: float = 2.0
    shadows: bool = True
    shadow_start: int = 300
    shadow_resolution: int | None = None
    shadow_receivers: str = "all"
    shadow_casters: str = "gaussians"
    light_response: bool = False
    rasterize_mode: str = "classic"
    object_position_rate: float = 1.0
    pose_rate_final: float = 0.1
    fixed_camera_weight: float = 1.0
    fixed_camera_share: float | None = None
    sh_degree: int = 2
    sh_every: int = 500
    refine_camera: bool = False
    exposure: bool = True
    backend: str = "auto"
    device: str = "auto"
    compile: str = "auto"
    eval_every: int = 250
    log_every: int = 50
    seed: int = 0


#: iterations of a CUDA run by default: where the held-out PSNR levels off. On an H100,
#: sim_pick_place_small (320x240, 120 frames) reached 38.4 dB about 10 000 iterations (averaged
#: over 9 000-11 000) against 38.6 over 12 500-15 000 and 37.0 about 3 000; the paper's 30 000
#: would spend two thirds of the time on the last few tenths of a dB
#: (benchmarks/results_device/gpu_long/long_pp_30000.json)
GPU_ITERS = 10_000


def default_iters(device: str) -> int:
    """Iterations when none are asked for: ``TrainConfig.iters`` (3000, about 1.5 dB short of the
    plateau, for the CPU's time) on the CPU, :data:`GPU_ITERS` on CUDA (``device`` as
    :func:`resolve_device` returns it)."""
    return GPU_ITERS if device.startswith("cuda") else TrainConfig.iters


COMPILE_CHOICES = ("auto", "on", "off")
#: TrainConfig.shadow_receivers' values (manisplat.scene.shadows.RECEIVERS, here without torch)
SHADOW_RECEIVERS = ("all", "background", "shaded")
#: TrainConfig.shadow_casters' values
SHADOW_CASTERS = ("meshes", "gaussians")
#: TrainConfig.rasterize_mode's values (manisplat.splat.RASTERIZE_MODES, here without torch)
RASTERIZE_MODES = ("classic", "antialiased")
#: manisplat-reconstruct --rasterize-mode's choices (:func:`resolve_rasterize_mode`)
RASTERIZE_CHOICES = ("auto", *RASTERIZE_MODES)


def resolve_rasterize_mode(name: str, cameras: int) -> str:
    """The rasterize mode of a run training ``cameras`` cameras, for ``name``: "classic",
    "antialiased", or "auto": antialiased with several cameras (a wrist camera's close-ups and the
    head camera a metre away see the same Gaussians at scales 10-20 times apart), classic with one
    (docs/benchmarks.md, antialiased splats)."""
    if name not in RASTERIZE_CHOICES:
        raise ValueError(f"unknown rasterize mode {name!r}; choose one of {', '.join(RASTERIZE_CHOICES)}")
    if name == "auto":
        return "antialiased" if cameras > 1 else "classic"
    return name


#: manisplat-reconstruct --sh-degree's choices (:func:`resolve_sh_degree`)
SH_DEGREE_CHOICES = ("auto", "0", "1", "2", "3")


def resolve_sh_degree(name: str, cameras: int) -> int:
    """The view-dependent colour bands of a run training ``cameras`` cameras, for ``name``: "0" to
    "3", or "auto": 3 with several cameras (wrist cameras see each surface from many directions; a
    third band drew every full image of the Cobot Magic samples 0.02-0.46 dB better), and
    ``TrainConfig.sh_degree`` (2) with one fixed camera, whose views of a surface barely turn
    (docs/benchmarks.md, a third band of view-dependent colour)."""
    if name not in SH_DEGREE_CHOICES:
        raise ValueError(f"unknown SH degree {name!r}; choose one of {', '.join(SH_DEGREE_CHOICES)}")
    if name == "auto":
        return 3 if cameras > 1 else TrainConfig.sh_degree
    return int(name)


#: manisplat-reconstruct --light-response's choices (:func:`resolve_light_response`)
LIGHT_RESPONSE_CHOICES = ("auto", "on", "off")


def resolve_light_response(name: str, riding: bool) -> bool:
    """Whether the moving parts learn their response to the light (``TrainConfig.light_response``),
    for ``name``: "on", "off", or "auto": on where a camera riding on an arm is trained (it sees
    its gripper from one direction whatever the arm does, so only this follows the light; on the
    Cobot Magic samples the wrist cameras' full images gain 1.0-3.4 dB, the head camera's 0.5;
    docs/benchmarks.md, the moving parts' response to the light), off with fixed cameras only,
    whose view-dependent colour turns with the parts (not measured there yet)."""
    if name not in LIGHT_RESPONSE_CHOICES:
        raise ValueError(f"unknown light response {name!r}; choose one of {', '.join(LIGHT_RESPONSE_CHOICES)}")
    return riding if name == "auto" else name == "on"


#: "auto" compiles a CUDA run of at least this many iterations: on an H100, over whole runs of
#: sim_pick_place_small (densification, held-out estimates, 65 600 Gaussians), an iteration took
#: 39.4 ms eagerly (gpu_eager/tests_long_pp_10000.json) and 19.7 ms compiled after about 240 s of
#: compiling (gpu_long/long_pp_30000.json): the compiled run is ahead from about 12 200 iterations
#: on (the SH bands compile nothing since, about 90 s less, not yet measured)
COMPILE_MIN_ITERS = 12_500


def resolve_compile(name: str, device_type: str, iters: int) -> str | None:
    """The ``torch.compile`` mode training runs its iteration in (:mod:`manisplat.compilation`),
    or None (eager), for ``name``: "on", "off", or "auto": on for a CUDA run of at least
    :data:`COMPILE_MIN_ITERS` iterations (where the compilation pays for itself); off on the CPU,
    where compiling costs minutes and saves a few per cent (README, the CPU iteration)."""
    if name not in COMPILE_CHOICES:
        raise ValueError(f"unknown compile setting {name!r}; choose one of {', '.join(COMPILE_CHOICES)}")
    if name == "auto":
        name = "on" if device_type == "cuda" and iters >= COMPILE_MIN_ITERS else "off"
    return "default" if name == "on" else None


DEVICES = ("auto", "cpu", "cuda")
GPU_HINT = "pip install 'manisplat[gpu]'"


class DeviceUnavailable(RuntimeError):
    """The requested device (or the backend it needs) cannot be used here; the message says why."""


def resolve_device(name: str, backend: str = "auto") -> str:
    """The torch device string training runs on, for ``name`` ("auto", "cpu", "cuda", "cuda:N").

    "auto" is "cuda" when torch sees a CUDA device (and ``backend`` is not "cpu"), else "cpu". For a CUDA device with the
    ``gsplat`` rasterizer (``backend`` "auto" or "gsplat"), gsplat must import. Nothing falls
    back: an unusable device raises :class:`DeviceUnavailable` naming what is missing.
    """
    import torch

    if name not in DEVICES and not name.startswith("cuda:"):
        raise ValueError(f"unknown device {name!r}; choose one of {', '.join(DEVICES)} (or cuda:N)")
    if name == "auto":  # the C++ backend asked for by name keeps training on the CPU
        name = "cuda" if torch.cuda.is_available() and backend != "cpu" else "cpu"
    if name == "cpu":
        if backend == "gsplat":
            raise DeviceUnavailable("the 'gsplat' backend runs on CUDA only; pass --device cuda or another --backend")
        return "cpu"
    if not torch.cuda.is_available():
        built = torch.version.cuda
        raise DeviceUnavailable(
            f"--device {name}: CUDA is not available here (torch {torch.__version__}, "
            f"{'built with CUDA ' + built + ' but no GPU/driver found' if built else 'a CPU-only build'}); "
            f"use --device cpu, or install a CUDA build of torch and {GPU_HINT}")
    index = int(name.partition(":")[2] or 0)
    if index >= torch.cuda.device_count():
        raise DeviceUnavailable(f"--device {name}: only {torch.cuda.device_count()} CUDA device(s) here")
    if backend == "cpu":
        raise DeviceUnavailable("the 'cpu' backend takes CPU tensors; with --device cuda use --backend auto/gsplat/torch")
    if backend in ("auto", "gsplat"):
        try:
            import gsplat  # noqa: F401
        except ImportError as exc:
            raise DeviceUnavailable(f"--device {name} renders with gsplat, which is not installed ({exc}); "
                                    f"{GPU_HINT} (or --backend torch, ~80x slower)") from exc
    return name


#: manisplat-reconstruct's mask-loss weight by where the masks come from (:func:`resolve_lambda_mask`)
MASK_LOSS_WEIGHTS = {"episode": 1.0, "drawn": 0.0}


#: manisplat-reconstruct's smoothness weight by whether a camera riding on an arm is trained
#: (:func:`resolve_lambda_smooth`)
SMOOTHNESS_WEIGHTS = {"fixed": 0.0, "riding": 1.0}


def resolve_lambda_smooth(weight: float | None, riding: bool) -> float:
    """The pose corrections' smoothness weight: ``weight`` when one is given (``--lambda-smooth``),
    else by the cameras trained (:data:`SMOOTHNESS_WEIGHTS`): 1 where a camera rides on an arm (a
    wrist camera), whose close views, posed by each frame's kinematics, jittered the corrections by
    millimetres and cost the wrist images 0.3-1.0 dB; 0 with fixed cameras only, where it held back
    corrections the images asked for (docs/benchmarks.md, the corrections' smoothness)."""
    if weight is not None:
        return weight
    return SMOOTHNESS_WEIGHTS["riding" if riding else "fixed"]


#: manisplat-reconstruct's weight of a fixed camera's gradients on the objects' Gaussians by whether a
#: camera riding on an arm is trained too (:func:`resolve_fixed_camera_weight`)
FIXED_CAMERA_WEIGHTS = {"fixed": 1.0, "riding": 30.0}


def resolve_fixed_camera_weight(weight: float | None, riding: bool) -> float:
    """The factor on a fixed camera's gradients on the objects' Gaussians: ``weight`` when one is
    given (``--fixed-camera-weight``), else by the cameras trained (:data:`FIXED_CAMERA_WEIGHTS`):
    30 where a camera rides on an arm (about the ratio of a wrist camera's gradients on an object's
    Gaussians to the head camera's: 17-19 on their colour, 26-30 on their positions; on the Cobot
    Magic samples the head camera's object region is drawn 2.7-3.5 dB better, as well as the head
    camera alone draws it, the wrist cameras' full images within 0.1 dB), 1 with fixed cameras
    only, which see the objects at like scales (docs/benchmarks.md, the head camera's say in how
    the objects look)."""
    if weight is not None:
        return weight
    return FIXED_CAMERA_WEIGHTS["riding" if riding else "fixed"]


#: manisplat-reconstruct --fixed-camera-share's word for every camera's frames alike (the share None)
SHARE_ALIKE = "alike"
#: manisplat-reconstruct --fixed-camera-share's words (besides a share): auto
#: (:func:`resolve_fixed_camera_share`) and alike
FIXED_CAMERA_SHARE_WORDS = ("auto", SHARE_ALIKE)
#: the fixed cameras' share of the iterations that auto gives from :data:`GPU_ITERS` iterations on
AUTO_FIXED_CAMERA_SHARE = 0.5


def resolve_fixed_camera_share(share: str | float, riding: bool, iters: int) -> float | None:
    """``TrainConfig.fixed_camera_share`` of a run of ``iters`` iterations, ``riding``: a camera
    riding on an arm trained beside the fixed ones. ``share``: a number in (0, 1) (refused with
    fixed cameras only: there is nothing to share with), "alike" (None: every camera's frames
    alike) or "auto": :data:`AUTO_FIXED_CAMERA_SHARE` where a camera rides on an arm and the run
    has :data:`GPU_ITERS` iterations or more (the CUDA default), alike otherwise. At 10 000
    iterations the head camera drawn in half of them met the Cobot Magic goals on both samples
    (its full image 35.3 dB, the handover's object region 28.1; alike 34.9 / 27.6), the wrist
    cameras 0.2-0.7 dB lower and still over theirs; at 3000 the wrist cameras had no iterations to
    spare (two of four under 30 dB, one alike) and the head camera stayed short either way
    (docs/benchmarks.md, the head camera drawn in half the iterations)."""
    if share not in FIXED_CAMERA_SHARE_WORDS:
        if not 0.0 < float(share) < 1.0:
            raise ValueError(f"a fixed camera's share of the iterations must be between 0 and 1, both excluded; "
                             f"got {share!r}")
        if not riding:
            raise ValueError("no camera riding on an arm is trained; it shares the iterations between fixed and "
                             "riding cameras")
        return float(share)
    if share == "auto" and riding and iters >= GPU_ITERS:
        return AUTO_FIXED_CAMERA_SHARE
    return None


def resolve_lambda_mask(weight: float | None, masks_drawn: bool) -> float:
    """The dynamic-mask loss's weight: ``weight`` when one is given (``--lambda-mask``), else by where
    the masks come from (:data:`MASK_LOSS_WEIGHTS`): 1 with the episode's own masks (the simulator's,
    a segmenter's), 0 with masks drawn by the reconstruction (the robot's from its model, objects
    segmented from depth from a click): pulling the rendered alpha to those approximate outlines
    cost the object region 0.2-4.1 dB held out at 3000 iterations (docs/benchmarks.md, no mask
    loss against drawn masks)."""
    if weight is not None:
        return weight
    return MASK_LOSS_WEIGHTS["drawn" if masks_drawn else "episode"]
