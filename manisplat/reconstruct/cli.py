"""manisplat-reconstruct: train the Gaussian scene graph of one episode, or of several episodes
of one scene (:mod:`manisplat.reconstruct.fusion`), and write the twin.

Exit status (:mod:`manisplat.exit_codes`): 0 done; 1 the training or the evaluation failed; 2 bad
arguments or an episode that cannot be reconstructed (a clear message says why), an ``--out`` that
holds earlier results without ``--overwrite`` or ``--resume``; 3 no usable ``--device``; 130
interrupted (checkpoint saved).

Only argparse and light modules are imported until the arguments are accepted: ``--help`` and
usage errors answer at once; torch and OpenCV load when the work starts.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from functools import partial
from pathlib import Path

from manisplat.align.phases import DEFAULT_TAU
from manisplat.cli_args import (add_version, bounded, finite, non_negative, numbers, open_fraction_or,
                                positive)
from manisplat.exit_codes import ExitCode, exit_status_help
from manisplat.output_folder import check_output_folder
from manisplat.reconstruct.config import (AUTO_FIXED_CAMERA_SHARE, COMPILE_CHOICES, COMPILE_MIN_ITERS,
                                          FIXED_CAMERA_SHARE_WORDS, GPU_ITERS, LIGHT_RESPONSE_CHOICES,
                                          RASTERIZE_CHOICES, SH_DEGREE_CHOICES, SHADOW_CASTERS, SHADOW_RECEIVERS,
                                          DeviceUnavailable, TrainConfig, default_iters, resolve_compile, resolve_device,
                                          resolve_fixed_camera_share, resolve_fixed_camera_weight, resolve_lambda_mask,
                                          resolve_lambda_smooth, resolve_light_response, resolve_rasterize_mode,
                                          resolve_sh_degree)
from manisplat.threads import THREADS_HELP, use_threads

log = logging.getLogger("manisplat.reconstruct")
CHECKPOINT = "checkpoint.pt"

EPILOG = f"""\
output folder: --out must be new or empty. One that holds anything is refused (exit 2) unless
  --overwrite (the outputs an earlier run wrote there, listed below, are removed first; other
  files are kept) or --resume (continue from OUT/{CHECKPOINT}).

outputs: twin.json + twin.pt (the twin: manisplat.twin.Twin.load(OUT) renders any state),
  background.ply, robot_<link>.ply, object_<name>.ply (3DGS PLY), object_poses.csv
  (object_poses_<name>.csv with several objects), phases.csv, renders/test/ (held-out renders),
  renders/sheets/ (ground truth | render | error), pose_plot.png, metrics.json (PSNR dB, SSIM,
  pose error cm/deg), exposure.csv (each frame's fitted colour gains), camera_refined.json (the
  camera as the reconstruction found it: `manisplat-calibrate apply` writes it into an episode),
  {CHECKPOINT}. The episode format: docs/episode-format.md.

""" + exit_status_help({
    ExitCode.OK: "done",
    ExitCode.FAILED: "the training failed (the rasterizer did not build), or the evaluation failed after the\n"
                     "twin was written",
    ExitCode.BAD_INPUT: "bad arguments; an episode that cannot be reconstructed (the file and field are named),\n"
                        "a damaged checkpoint for --resume; an --out in use without --overwrite or --resume",
    ExitCode.DEVICE: "--device names a device that is not usable (no CUDA build, no GPU)",
    ExitCode.INTERRUPTED: "interrupted (a checkpoint is saved: continue with --resume)",
})


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="manisplat-reconstruct",
        description="Reconstruct one episode as a Gaussian scene graph (static background, robot links driven "
                    "by forward kinematics, objects with per-frame poses), aligned with the task's Motion/Skill "
                    "phases. Writes PLYs, object poses, phases, held-out renders, a pose plot and metrics.json. "
                    "Several episodes of one scene (the same table, camera and objects; the objects elsewhere) "
                    "make one twin: one background, robot and model per object, a source demonstration per "
                    "episode; an episode of another scene is refused, named.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("episodes", type=Path, nargs="+", metavar="EPISODE",
                   help="episode folder (docs/episode-format.md; format version 2: several arms in its world frame); "
                        "several, or a folder of episode folders, for one twin of them all (each needs depth and "
                        "masks; one fixed camera)")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder: created; must be new or empty unless --overwrite or --resume")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the results of an earlier run in --out (its files are removed first)")
    p.add_argument("--robot", help="robot description: a URDF path or builtin:agilex_piper "
                                   "(default: the episode's robot.description)")
    p.add_argument("--cameras", type=_names, metavar="NAME,...",
                   help="the cameras to train on, in an episode with several (default: all): the fixed one "
                        "among them seeds the scene and is checked against the robot; the others (wrist "
                        "cameras) are posed at each frame by forward kinematics and trained at once")
    p.add_argument("--iters", type=positive(int), default=None,
                   help=f"training iterations (default {TrainConfig.iters} on the CPU, {GPU_ITERS} on CUDA, where the "
                        "held-out PSNR levels off)")
    p.add_argument("--backend", default="auto", choices=("auto", "cpu", "torch", "gsplat"),
                   help="rasterizer: auto (gsplat on CUDA, else the C++ CPU backend), cpu, torch (slow reference), gsplat")
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"),
                   help="where training runs: auto (CUDA when available, else cpu; the default), cpu, or cuda "
                        "(needs a CUDA build of torch and gsplat: pip install 'manisplat[gpu]'); exit 3 if unusable")
    p.add_argument("--threads", type=positive(int), metavar="N", help=THREADS_HELP)
    p.add_argument("--compile", default="auto", choices=COMPILE_CHOICES,
                   help="run the training iteration's tensor work through torch.compile: auto (on for CUDA runs "
                        f"of {COMPILE_MIN_ITERS} iterations or more: 2x faster iterations after about 4 minutes of "
                        "compiling on an H100; off on the CPU, where compiling costs more than it saves), on, off")
    p.add_argument("--tau", type=positive(), default=DEFAULT_TAU,
                   help=f"Skill distance threshold in metres between the TCP and the object (default {DEFAULT_TAU}; "
                        "the paper's 0.2 is in its own scene units)")
    p.add_argument("--no-shadows", action="store_true", help="do not model the moving parts' cast shadows")
    p.add_argument("--shadow-receivers", default="all", choices=SHADOW_RECEIVERS,
                   help="what the cast shadows darken: all (the background and the moving parts: the gripper's "
                        "shadow on the object; default), background (the parts keep recorded shadows in their colour) "
                        "or shaded (as all, and the objects lit by their surfaces' angle to the light: a face turned "
                        "to a new yaw takes that pose's light)")
    p.add_argument("--light-response", default="auto", choices=LIGHT_RESPONSE_CHOICES,
                   help="let the links' and objects' colours follow the shadows' light as each part turns under it "
                        "(a gain per Gaussian on the light's direction in the part's frame): auto (default: on where a "
                        "camera riding on an arm is trained, which sees its fingers from one direction whatever the "
                        "arm does), on, off")
    p.add_argument("--shadow-casters", default="gaussians", choices=SHADOW_CASTERS,
                   help="what casts the links' shadows: gaussians (the links' fitted Gaussians, whose shadows come out "
                        "wider; default) or meshes (the robot description's link meshes: the links' outlines)")
    p.add_argument("--rasterize-mode", default="auto", choices=RASTERIZE_CHOICES,
                   help="how splats smaller than a pixel are drawn: classic (dilated to a pixel at full opacity), "
                        "antialiased (dilated at the opacity that keeps their integral: Gaussians fitted to a wrist "
                        "camera's close-ups, seen from the head camera) or auto (default: antialiased when several "
                        "cameras are trained, classic with one)")
    p.add_argument("--sh-degree", default="auto", choices=SH_DEGREE_CHOICES,
                   help="bands of view-dependent colour (spherical harmonics) each Gaussian learns: 0-3, or auto "
                        "(default: 3 when several cameras are trained, whose views turn around each surface; 2 with "
                        "one)")
    p.add_argument("--fixed-camera-weight", type=positive(), default=None, metavar="W",
                   help="the factor on the gradients a fixed camera's frames give the objects' Gaussians (default: "
                        "30 when a camera riding on an arm is trained too, whose close-ups would otherwise decide alone "
                        "how the objects look; 1 with fixed cameras only)")
    p.add_argument("--fixed-camera-share", type=open_fraction_or(FIXED_CAMERA_SHARE_WORDS), default="auto",
                   metavar="{auto,alike,S}",
                   help="the share S of the iterations that draw a fixed camera's frame where cameras riding on an "
                        "arm are trained too; alike: every camera's frames alike (a third for the head camera beside "
                        f"two wrist cameras); auto (default): {AUTO_FIXED_CAMERA_SHARE:g} from {GPU_ITERS} iterations "
                        "on (the CUDA default), alike below")
    p.add_argument("--object-position-rate", type=positive(), default=TrainConfig.object_position_rate, metavar="R",
                   help="the objects' Gaussians' position learning rate as a fraction of the scene's (default "
                        f"{TrainConfig.object_position_rate:g}; 0.3 keeps a few-centimetre object's Gaussians nearer "
                        "its faces: docs/benchmarks.md, policies trained on the output)")
    p.add_argument("--pose-rate-final", type=bounded(1e-6, 1.0), default=TrainConfig.pose_rate_final, metavar="F",
                   help="the object poses' learning rate at the end of training as a fraction of its start (default "
                        f"{TrainConfig.pose_rate_final:g}: tenfold over training; 1: constant, which let a resting "
                        "object's pose wander a millimetre; 0.01, the Gaussians' positions' decay, corrected less of "
                        "the pseudo ground truth)")
    p.add_argument("--no-densify", action="store_true", help="keep the initial Gaussians (no clone/split/prune)")
    p.add_argument("--refine-camera", action="store_true", help="also optimise a correction of the camera extrinsic")
    p.add_argument("--keep-extrinsic", action="store_true",
                   help="use the episode's camera extrinsic as it is (default: check it against the robot's depth and "
                        "correct it; the result goes to camera_refined.json)")
    p.add_argument("--no-exposure", action="store_true",
                   help="no per-frame exposure / white-balance gains (for a camera with fixed exposure and white balance)")
    p.add_argument("--lambda-app", type=non_negative(), default=1.0, help="weight of the masked appearance loss (default 1)")
    p.add_argument("--lambda-mask", type=non_negative(), default=None,
                   help="weight of the dynamic-mask loss (default: 1 with the episode's masks, 0 with masks drawn "
                        "here, whose approximate outlines cost the object region)")
    p.add_argument("--lambda-pose", type=non_negative(), default=TrainConfig.lambda_pose,
                   help=f"weight of the pose prior loss (default {TrainConfig.lambda_pose:g}: light enough for the images "
                        "to correct the pseudo ground truth by millimetres; 1, the paper's, keeps it)")
    p.add_argument("--lambda-smooth", type=non_negative(), default=None,
                   help="weight of the pose corrections' smoothness loss: each moving frame's against its trained "
                        "neighbours' (default: 1 when a camera riding on an arm is trained, whose close views jitter "
                        "the corrections; 0 with fixed cameras only)")
    inputs = p.add_argument_group(
        "episodes without depth or masks",
        "Without masks, the robot's are drawn from its meshes at each frame's forward kinematics and the "
        "object is segmented from a prompt in the first frame: with depth, the region above the table plane "
        "(not robot) at the point or in the box, followed through the frames; without depth, GrabCut in the "
        "box, then the object's model at its tracked pose. Without depth, the table is the plane z = "
        "--table-z of the base frame and objects start as billboards standing on it.")
    inputs.add_argument("--object-point", type=_named(_pixel_pair), action="append", default=[],
                        metavar="[NAME=]U,V",
                        help="a pixel on the object in the first frame (column, row); once per object, each "
                             "named when several (box=152,160)")
    inputs.add_argument("--object-box", type=_named(_pixel_box), action="append", default=[],
                        metavar="[NAME=]X0,Y0,X1,Y1",
                        help="a box around the object in the first frame (pixels, inclusive); once per object")
    inputs.add_argument("--object-name", default="object",
                        help="name of the one prompted object when the episode lists none (default 'object')")
    inputs.add_argument("--no-depth", action="store_true", help="ignore the episode's depth (monocular reconstruction)")
    inputs.add_argument("--no-masks", action="store_true",
                        help="ignore the episode's masks and draw/segment them (the episode's still score the regions)")
    inputs.add_argument("--table-z", type=finite(), default=0.0,
                        help="table height in the base frame, metres, for a start without depth (default 0)")
    p.add_argument("--plan", action="store_true", help="print the plan (what is reconstructed, what is skipped) and exit")
    p.add_argument("--resume", action="store_true",
                   help=f"continue from OUT/{CHECKPOINT} (a new run when OUT is new or empty)")
    p.add_argument("--checkpoint-every", type=positive(int), default=500, help="iterations between checkpoints (default 500)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar, warnings only")
    return add_version(p)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        args.episodes = _episode_folders(args.episodes)
        if len(args.episodes) > 1:
            _check_fusable(args)
        if args.light_response == "on" and args.no_shadows:
            raise ValueError("--light-response on follows the shadows' light, which --no-shadows leaves out")
        prompt = _prompt(args)
        if not args.plan:
            _check_out(args)
    except ValueError as exc:
        parser.error(str(exc))
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO, format="%(message)s")
    return _run(args, prompt)


def _episode_folders(paths: list[Path]) -> list[Path]:
    """The episodes named: a folder holding no episode.json but episode folders stands for them,
    in name order (any other path is left for loading to judge)."""
    out = []
    for path in paths:
        inner = sorted(p for p in path.iterdir() if (p / "episode.json").is_file()) \
            if path.is_dir() and not (path / "episode.json").exists() else []
        out += inner or [path]
    if len(set(map(str, out))) != len(out):
        raise ValueError("an episode is named twice")
    return out


def _check_fusable(args: argparse.Namespace) -> None:
    """Refuse options a fused reconstruction of several episodes does not take."""
    single = [flag for flag, on in (("--object-point", args.object_point), ("--object-box", args.object_box),
                                    ("--no-masks", args.no_masks), ("--no-depth", args.no_depth),
                                    ("--cameras", args.cameras)) if on]
    if single:
        raise ValueError(f"{', '.join(single)}: for one episode; several are reconstructed from each episode's depth "
                         "and masks and its one fixed camera")


def _check_out(args: argparse.Namespace) -> None:
    """Refuse an ``--out`` holding anything, unless ``--overwrite`` or ``--resume`` says what to do."""
    if args.overwrite and args.resume:
        raise ValueError("--overwrite and --resume exclude each other")
    in_use = check_output_folder(args.out, allowed=args.overwrite or args.resume,
                                 refusal=" (an earlier run's results?); pass --overwrite to replace them, --resume "
                                         "to continue its training, or choose another folder")
    if in_use and args.resume and not (args.out / CHECKPOINT).is_file():
        raise ValueError(f"--resume: {args.out} holds no {CHECKPOINT} to continue from")


def _run(args: argparse.Namespace, prompt: list[tuple[str, tuple | None, tuple | None]]) -> int:
    """Load, plan, align, train, write the twin, then evaluate it."""
    start = time.perf_counter()
    use_threads(args.threads)  # before torch loads OpenMP (manisplat.threads)
    import torch

    from manisplat.episode import EpisodeFormatError
    from manisplat.reconstruct.data import ReconstructionInputError, load_episode_data
    from manisplat.reconstruct.outputs import remove_outputs, write_evaluation, write_twin
    from manisplat.reconstruct.plan import make_plan
    from manisplat.robot import RobotModelError
    from manisplat.splat import BackendUnavailable

    try:
        device = resolve_device(args.device, args.backend)
    except DeviceUnavailable as exc:
        print(f"error: {exc}", file=sys.stderr)
        return ExitCode.DEVICE
    iters = args.iters if args.iters is not None else default_iters(device)
    compiled = resolve_compile(args.compile, device.partition(":")[0], iters)
    fused = None
    try:
        if len(args.episodes) > 1:
            if args.plan:
                for path in args.episodes:
                    print(f"{path}:\n{make_plan(load_episode_data(path, robot=args.robot)).summary()}")
                print(_training_summary(args, device, iters, compiled))
                return ExitCode.OK
            fused = _build_fused(args, _config(args, device, iters, compiled, cameras=1, masks_drawn=False,
                                               riding=False))
            rec, alignments = fused.reconstruction, fused.alignments
        else:
            built = _build_one(args, prompt, partial(_config, args, device, iters, compiled),
                               _training_summary(args, device, iters, compiled))
            if built is None:
                return ExitCode.OK
            rec, alignments = built
    except (ReconstructionInputError, EpisodeFormatError, RobotModelError, FileNotFoundError, NotImplementedError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return ExitCode.BAD_INPUT
    if args.overwrite:
        removed = remove_outputs(args.out)
        if removed:
            log.info("--overwrite: removed %d files of an earlier run from %s", removed, args.out)
    args.out.mkdir(parents=True, exist_ok=True)
    checkpoint = args.out / CHECKPOINT
    if args.resume and checkpoint.exists():
        # on the host first, whichever device wrote it; load_state_dict moves it to this run's device
        # tensors and plain containers only: a checkpoint is never unpickled as code
        try:
            rec.load_state_dict(torch.load(checkpoint, weights_only=True, map_location="cpu"))
        except Exception as exc:  # torch raises several types for damaged or foreign files
            print(f"error: {checkpoint}: cannot resume from it ({type(exc).__name__}: {exc}); "
                  f"start a new run with --overwrite", file=sys.stderr)
            return ExitCode.BAD_INPUT
        log.info("resumed from %s at iteration %d", checkpoint, rec.step)

    def save(r) -> None:
        if r.step % args.checkpoint_every == 0:
            r.save_checkpoint(checkpoint)

    try:
        trained_from, train_start = rec.step, time.perf_counter()
        rec.train(progress=not args.quiet, callback=save)
        train_end = time.perf_counter()
    except BackendUnavailable as exc:
        print(f"error: {exc}", file=sys.stderr)
        return ExitCode.FAILED
    except KeyboardInterrupt:
        rec.save_checkpoint(checkpoint)
        print(f"\ninterrupted at iteration {rec.step}; continue with --resume", file=sys.stderr)
        return ExitCode.INTERRUPTED
    rec.save_checkpoint(checkpoint)
    spans = fused.spans if fused is not None else None
    write_twin(rec, alignments, args.out, spans)
    try:
        metrics = write_evaluation(rec, alignments, args.out, wall_s=time.perf_counter() - start,
                                   ms_per_iter=1e3 * (train_end - train_start) / max(rec.step - trained_from, 1),
                                   spans=spans, camera=fused.camera.to_dict(spans) if fused is not None else None)
    except Exception as exc:  # the trained twin is on disk: report, keep it, fail
        log.debug("evaluation failed", exc_info=True)
        print(f"error: the twin is trained and written to {args.out} (twin.json/.pt, PLYs, object poses, phases, "
              f"{CHECKPOINT}), "
              f"but its evaluation failed: {type(exc).__name__}: {exc}", file=sys.stderr)
        return ExitCode.FAILED
    print(_summary(metrics, args.out))
    return ExitCode.OK


def _training_summary(args: argparse.Namespace, device: str, iters: int, compiled: str | None) -> str:
    """One line of what training will do on ``device``: the budget and where it comes from, eager or
    compiled, densification (the plan prints it; the log says it before training)."""
    if args.iters is not None:
        budget = f"{iters} iterations (--iters)"
    else:
        why = ("the CUDA default: the held-out PSNR's plateau on an H100" if device.startswith("cuda")
               else f"the CPU default, about 1.5 dB short of the plateau that CUDA's {GPU_ITERS} reach")
        budget = f"{iters} iterations ({why}; --iters to change)"
    mode = ("the iteration compiled by torch.compile (about 4 minutes on an H100, in the first 1 250 iterations)"
            if compiled else f"the iteration eager (--compile on to compile; auto compiles CUDA runs of {COMPILE_MIN_ITERS} "
            "iterations or more)")
    c = TrainConfig
    densify = ("densification off (--no-densify)" if args.no_densify else
               f"densification every {c.refine_every} iterations from {c.refine_start} to {int(c.refine_stop_fraction * iters)}")
    return f"training      on {device} (rasterizer backend {args.backend}), {budget}; {mode}; {densify}"


def _chosen_by(flag: str, given: float | None, riding: bool) -> str:
    """What chose a setting whose default depends on whether a camera riding on an arm is trained."""
    if given is not None:
        return flag
    return "a camera riding on an arm is trained" if riding else "fixed cameras only"


def _config(args: argparse.Namespace, device: str, iters: int, compiled: str | None, cameras: int,
            masks_drawn: bool, riding: bool) -> TrainConfig:
    """The training configuration of a run training ``cameras`` cameras, with masks drawn by the
    reconstruction (``masks_drawn``) or the episode's, ``riding``: one of them on an arm (logged)."""
    log.info("%s", _training_summary(args, device, iters, compiled))
    rasterize_mode = resolve_rasterize_mode(args.rasterize_mode, cameras)
    log.info("splats drawn %s (--rasterize-mode %s, %d camera%s trained)", rasterize_mode, args.rasterize_mode,
             cameras, "s" if cameras > 1 else "")
    sh_degree = resolve_sh_degree(args.sh_degree, cameras)
    log.info("view-dependent colour of degree %d (--sh-degree %s)", sh_degree, args.sh_degree)
    light_response = resolve_light_response(args.light_response, riding) and not args.no_shadows
    log.info("the moving parts' response to the light %s (--light-response %s%s)", "learned" if light_response else "off",
             args.light_response, "; no shadows, no light" if args.no_shadows else "")
    lambda_mask = resolve_lambda_mask(args.lambda_mask, masks_drawn)
    log.info("mask loss weight %g (%s; masks %s)", lambda_mask,
             "--lambda-mask" if args.lambda_mask is not None else "by the masks' source",
             "drawn here" if masks_drawn else "the episode's")
    lambda_smooth = resolve_lambda_smooth(args.lambda_smooth, riding)
    log.info("pose corrections' smoothness weight %g (%s)", lambda_smooth,
             _chosen_by("--lambda-smooth", args.lambda_smooth, riding))
    fixed_camera_weight = resolve_fixed_camera_weight(args.fixed_camera_weight, riding)
    log.info("a fixed camera's gradients on the objects' Gaussians weighed %g (%s)", fixed_camera_weight,
             _chosen_by("--fixed-camera-weight", args.fixed_camera_weight, riding))
    try:
        fixed_camera_share = resolve_fixed_camera_share(args.fixed_camera_share, riding, iters)
    except ValueError as exc:
        from manisplat.reconstruct.data import ReconstructionInputError

        raise ReconstructionInputError(f"--fixed-camera-share: {exc}") from None
    if riding:
        log.info("%s (--fixed-camera-share %s%s)", "every camera's frames drawn alike" if fixed_camera_share is None
                 else f"a fixed camera's frames drawn in {fixed_camera_share:g} of the iterations",
                 args.fixed_camera_share, f", {iters} iterations" if args.fixed_camera_share == "auto" else "")
    return TrainConfig(
        iters=iters, backend=args.backend, shadows=not args.no_shadows, shadow_receivers=args.shadow_receivers,
        light_response=light_response,
        shadow_casters=args.shadow_casters, rasterize_mode=rasterize_mode, sh_degree=sh_degree,
        fixed_camera_weight=fixed_camera_weight, fixed_camera_share=fixed_camera_share,
        object_position_rate=args.object_position_rate, pose_rate_final=args.pose_rate_final,
        densify=not args.no_densify, refine_camera=args.refine_camera, exposure=not args.no_exposure,
        lambda_app=args.lambda_app,
        lambda_mask=lambda_mask, lambda_pose=args.lambda_pose, lambda_smooth=lambda_smooth,
        seed=args.seed, device=device, compile=args.compile,
    )


def _build_one(args: argparse.Namespace, prompt, config, training: str):
    """Load, plan and align one episode: (reconstruction, alignments), or None after ``--plan``
    printed the plan and ``training`` (:func:`_training_summary`). ``config``: makes the training
    configuration, given the number of cameras trained, whether the masks are drawn here and whether
    a camera trained rides on an arm, once the plan is logged."""
    from manisplat.reconstruct.data import ReconstructionInputError, load_episode_data
    from manisplat.reconstruct.masks import ObjectPrompt, complete_masks
    from manisplat.reconstruct.pipeline import build
    from manisplat.reconstruct.plan import make_plan

    episode = args.episodes[0]
    reference, others = _cameras(episode, args.cameras)
    data = load_episode_data(episode, robot=args.robot, camera=reference, use_depth=not args.no_depth,
                             use_masks=not args.no_masks, progress=not args.quiet)
    views = {name: load_episode_data(episode, robot=args.robot, camera=name, use_depth=not args.no_depth,
                                     use_masks=not args.no_masks, load_meshes=False, progress=not args.quiet)
             for name in others}
    for view in views.values():
        view.robot = data.robot  # one model (with its meshes) for every camera
    masks_from_model = False
    masks_drawn = data.masks is None or any(view.masks is None for view in views.values())
    if data.masks is None:
        links = [name for name in data.robot.link_names if data.robot.visuals.get(name)]
        prompts = [ObjectPrompt(name, point=point, box=box) for name, point, box in prompt]
        masks_from_model = complete_masks(data, links, prompts, progress=not args.quiet)
    elif prompt:
        raise ReconstructionInputError("the episode has masks; --object-point/--object-box are for episodes "
                                       "without (add --no-masks to segment anew)")
    plan = make_plan(data)
    if args.plan:
        print(plan.summary())
        print(training)
        return None
    log.info("plan:\n%s", plan.summary())
    riding = any(view.riding for view in views.values())
    return build(data, plan, config(1 + len(views), masks_drawn, riding), tau=args.tau, table_z=args.table_z,
                 masks_from_model=masks_from_model, check_extrinsic=not args.keep_extrinsic, views=views,
                 progress=not args.quiet)


def _build_fused(args: argparse.Namespace, config: TrainConfig):
    """Load, check, plan and align several episodes of one scene (:func:`~manisplat.reconstruct.pipeline.build_fused`)."""
    from tqdm import tqdm

    from manisplat.reconstruct.data import load_episode_data
    from manisplat.reconstruct.pipeline import build_fused
    from manisplat.reconstruct.plan import make_plan

    datas = [load_episode_data(path, robot=args.robot) for path in
             tqdm(args.episodes, desc="loading episodes", unit="episode", disable=args.quiet)]
    plans = [make_plan(d) for d in datas]
    log.info("plan of %s (the first of %d episodes):\n%s", args.episodes[0].name, len(datas), plans[0].summary())
    return build_fused(datas, plans, config, tau=args.tau, check_extrinsic=not args.keep_extrinsic)


def _prompt(args: argparse.Namespace) -> list[tuple[str, tuple | None, tuple | None]]:
    """The object prompts as (name, point, box): one per object, each named when several."""
    prompts = [(name, point, None) for name, point in args.object_point] + \
        [(name, None, box) for name, box in args.object_box]
    if len(prompts) == 1:
        name = prompts[0][0] or args.object_name
        return [(name, *prompts[0][1:])]
    unnamed = [p for p in prompts if p[0] is None]
    if unnamed:
        raise ValueError(f"{len(prompts)} object prompts: name each (--object-point NAME=U,V, --object-box NAME=X0,..)")
    names = [p[0] for p in prompts]
    if len(set(names)) != len(names):
        raise ValueError(f"object prompts {names}: one point or box per object")
    return prompts


def _names(text: str) -> list[str]:
    """An argparse type for ``A,B,...``: the names, none empty, none twice."""
    names = [n.strip() for n in text.split(",")]
    if not all(names) or len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(f"{text!r}: expected distinct names separated by commas")
    return names


def _cameras(episode: Path, names: list[str] | None) -> tuple[str | None, list[str]]:
    """(the reference camera, the other cameras to train on) of ``names`` (None: every camera of
    the episode): the reference is the first fixed one; None for an episode with one camera."""
    from manisplat.episode import Episode
    from manisplat.episode.format import WORLD_MOUNT
    from manisplat.reconstruct.data import ReconstructionInputError

    cameras = Episode.open(episode).cameras
    if names is None:
        if len(cameras) == 1:
            return None, []
        names = list(cameras)
    unknown = [n for n in names if n not in cameras]
    if unknown:
        raise ReconstructionInputError(f"{episode}: no camera {', '.join(unknown)}; cameras: {', '.join(cameras)}")
    fixed = [n for n in names if cameras[n].mount in ("base", WORLD_MOUNT)]
    if not fixed:
        raise ReconstructionInputError(f"cameras {', '.join(names)}: none is fixed; one fixed camera (the head "
                                       "camera) must seed the scene")
    if len(cameras) == 1:
        return None, []
    return fixed[0], [n for n in names if n != fixed[0]]


def _named(parse):
    """An argparse type for ``[NAME=]VALUE``: (name or None, ``parse(VALUE)``)."""
    def parse_named(text: str):
        name, sep, value = text.rpartition("=")
        if sep and not name:
            raise argparse.ArgumentTypeError(f"{text!r}: the name before '=' is empty")
        return (name or None), parse(value)
    return parse_named


def _pixel_pair(text: str) -> tuple[float, float]:
    u, v = numbers((2,))(text)
    return u, v


def _pixel_box(text: str) -> tuple[int, int, int, int]:
    x0, y0, x1, y1 = (int(round(v)) for v in numbers((4,))(text))
    if not (x0 < x1 and y0 < y1):
        raise argparse.ArgumentTypeError(f"box {text!r}: need X0 < X1 and Y0 < Y1")
    return x0, y0, x1, y1


def _summary(metrics: dict, out: Path) -> str:
    """The closing lines: time, held-out quality, pose error (with units) and the files to open."""
    lines = [f"done in {metrics['wall_s']:.0f} s, {metrics['iters']} iterations; outputs in {out}/"]
    regions = ("full", "robot", "object")
    psnr, ssim = metrics.get("psnr") or {}, metrics.get("ssim") or {}
    if psnr:
        lines.append("held-out PSNR: " + ", ".join(f"{k} {psnr[k]:.2f} dB" for k in regions if psnr.get(k) is not None))
    fitted = metrics.get("psnr_colour_fitted") or {}
    if fitted and psnr.get("full") is not None and fitted.get("full", 0) - psnr["full"] > 0.5:
        lines.append("held-out PSNR with each frame's colour fitted on its static pixels (exposure): "
                     + ", ".join(f"{k} {fitted[k]:.2f} dB" for k in regions if fitted.get(k) is not None))
    if ssim:
        lines.append("held-out SSIM: " + ", ".join(f"{k} {ssim[k]:.3f}" for k in regions if ssim.get(k) is not None))
    for obj, err in metrics.get("pose", {}).items():
        base = metrics.get("pose_baseline", {}).get(obj)
        extra = f" (per-frame baseline: {base['et_cm']:.2f} cm, {base['er_deg']:.2f} deg)" if base else ""
        lines.append(f"pose error {obj}: {err['et_cm']:.2f} cm, {err['er_deg']:.2f} deg, mean over frames after "
                     f"a constant offset fitted to all frames{extra}")
        anchored = metrics.get("pose_anchored", {}).get(obj)
        if anchored:
            lines.append(f"pose error {obj}, start-anchored: {anchored['et_cm']:.2f} cm, {anchored['er_deg']:.2f} deg, "
                         f"mean over the {anchored['moved_frames']:.0f} frames after it first moves; where it is left: "
                         f"{anchored['final']['et_cm']:.2f} cm, {anchored['final']['er_deg']:.2f} deg")
    episodes = metrics.get("episodes")
    if episodes:
        lines.append(f"{len(episodes)} episodes, one twin; above: their means; each episode's in metrics.json "
                     "episodes (held-out PSNR full / robot / object dB):")
        lines += [f"  {name}: " + " / ".join(f"{e['psnr'][k]:.2f}" if e["psnr"].get(k) is not None else "-"
                                             for k in regions) for name, e in episodes.items()]
        for obj, err in metrics.get("pose_one_offset", {}).items():
            lines.append(f"pose error {obj} with one constant offset for every episode: {err['et_cm']:.2f} cm, "
                         f"{err['er_deg']:.2f} deg")
    camera = metrics.get("camera")
    if camera and episodes:
        lines.append("camera extrinsic checked in every episode (metrics.json camera): "
                     f"{sum(1 for e in camera['episodes'].values() if e['check'] and e['check']['applied'])} of "
                     f"{len(camera['episodes'])} corrections trusted, the twin's camera their mean or, with fewer "
                     "than half, as calibrated")
    elif camera:
        if camera["applied"]:  # camera_refined.json differs from the episode's camera: the advice changes it
            lines.append(f"camera extrinsic corrected by {camera['rotation_deg']:.3f} +- "
                         f"{camera['sigma_rotation_deg']:.3f} deg, {camera['translation_mm']:.2f} +- "
                         f"{camera['sigma_translation_mm']:.2f} mm (robot depth, 1 sigma); write it into the episode "
                         f"with `manisplat-calibrate apply {out / 'camera_refined.json'} EPISODE`")
        else:
            lines.append(f"camera extrinsic kept as recorded: {camera['reason']}")
        if camera.get("time_offset_ms") is not None:
            lines.append(f"camera/joint time offset {camera['time_offset_ms']:+.1f} +- {camera['sigma_time_offset_ms']:.1f} ms "
                         + ("(applied: joints re-paired)" if camera["time_applied"] else "(not applied)"))
    look = [name for name in ("pose_plot.png", "renders/sheets/", "metrics.json") if (out / name.rstrip("/")).exists()]
    lines.append("look at: " + ", ".join(str(out / name) + ("/" if name.endswith("/") else "") for name in look))
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
