"""manisplat-view: the twin, an episode or new demonstrations in the browser, or as a video.

Only argparse and light modules are imported until the arguments are accepted.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import logging
import signal
import sys
import threading
from pathlib import Path

from manisplat.cli_args import add_version, bounded, positive
from manisplat.exit_codes import ExitCode, exit_status_help
from manisplat.threads import THREADS_HELP, use_threads

log = logging.getLogger("manisplat.view")

EPILOG = """\
PATH is one of:
  an episode (episode.json, format version 1 or 2): every arm at its base and recorded joints (its
    meshes), every camera's frustum with the frame's image (a wrist camera moving with its link), the
    depth as points, the TCP paths; all in the episode's world frame (version 1: the arm's base);
  a reconstruction (manisplat-reconstruct --out, twin.json): the twin's Gaussians (background,
    links moved by forward kinematics, objects at their trained poses), the robot's meshes as a
    second layer, and the twin rendered by our rasterizer beside the recorded image (the source
    episode is looked for beside the folder or here, or given with --episode);
  an augmentation output (manisplat-augment --out): the same twin, a list of the demonstrations
    (the source first), every TCP path overlaid, the chosen one animated, its validation record.

The page has a timeline (play, frame, speed) and layer switches. The server binds to 127.0.0.1
unless --host says otherwise (0.0.0.0 exposes it to your network) and runs until Ctrl-C.

--video OUT.mp4 writes the demonstrations instead (H.264, no browser): an episode's images (its
cameras side by side under their names when it has several), a reconstruction's [recorded | twin]
side by side under a header naming them and the frame, an augmentation folder's demonstrations one
after another; --orbit DEG turns the camera about the scene over the video.

""" + exit_status_help({
    ExitCode.OK: "done (or the server stopped with Ctrl-C)",
    ExitCode.BAD_INPUT: "bad arguments; PATH cannot be shown (what is missing or damaged is named); an\n"
                        "existing --video file without --overwrite",
    ExitCode.INTERRUPTED: "--video interrupted (no video written)",
})


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="manisplat-view",
        description="See a twin, an episode or new demonstrations in the browser (viser), or write a video.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("path", type=Path, metavar="PATH", help="an episode, a reconstruction or an augmentation output")
    p.add_argument("--port", type=bounded(1, 65535, kind=int), default=8080,
                   help="port of the page (default %(default)s; the next free one when it is taken)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default %(default)s: this machine only)")
    p.add_argument("--twin", type=Path, metavar="RECON_DIR",
                   help="the reconstruction an augmentation folder was made from (default: its report's)")
    p.add_argument("--episode", type=Path, metavar="EP",
                   help="the episode a reconstruction was made from (default: its name, beside it or here)")
    p.add_argument("--video", type=Path, metavar="OUT.mp4", help="write a video instead of serving the page")
    p.add_argument("--threads", type=positive(int), metavar="N", help=THREADS_HELP)
    p.add_argument("--orbit", type=float, default=0.0, metavar="DEG",
                   help="with --video and a twin: turn the camera DEG degrees about the scene (default: 0, the "
                        "episode's camera)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --video file (default: refused)")
    p.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    return add_version(p)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.video is not None and args.video.exists() and not args.overwrite:
        parser.error(f"--video {args.video} exists; pass --overwrite to replace it")
    if args.orbit and args.video is None:
        parser.error("--orbit applies to --video only (in the browser, drag to orbit)")
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO, format="%(message)s")
    logging.getLogger("websockets").setLevel(logging.WARNING)  # one line per connection otherwise
    use_threads(args.threads)
    from manisplat.view.content import ViewInputError, load_content

    try:
        content = load_content(args.path, twin=args.twin, episode=args.episode)
    except (ViewInputError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return ExitCode.BAD_INPUT
    for note in content.notes:
        log.warning("not shown: %s", note)
    if args.video is not None:
        return _write_video(content, args)
    return _serve(content, args)


def _write_video(content, args: argparse.Namespace) -> int:
    from manisplat.view.video import write_video

    try:
        result = write_video(content, args.video, orbit_deg=args.orbit, progress=sys.stderr.isatty())
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return ExitCode.BAD_INPUT
    except KeyboardInterrupt:
        print("\ninterrupted: no video written", file=sys.stderr)
        return ExitCode.INTERRUPTED
    print(f"wrote {result.path}: {result.frames} frames, {result.width}x{result.height}, "
          f"{result.frames_per_s:.1f} frames/s")
    return ExitCode.OK


def _serve(content, args: argparse.Namespace) -> int:
    import viser

    from manisplat.view.app import Viewer

    with contextlib.redirect_stdout(io.StringIO()):  # viser prints its own banner; we print one line
        server = viser.ViserServer(host=args.host, port=args.port, verbose=False)
    viewer = Viewer(content, server)
    shown = {"episode": "episode" if len(content.arms) == len(content.cameras) == 1 else
             f"episode: arms {', '.join(content.arms)}; cameras {', '.join(content.cameras)}",
             "reconstruction": "twin", "augmentation": f"{len(content.demos)} demonstrations"}
    print(f"manisplat-view: {args.path} ({shown[content.kind]}) at http://{args.host}:{server.get_port()} "
          "(Ctrl-C stops)", flush=True)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())  # `kill` stops it as cleanly as Ctrl-C
    try:
        while not stop.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        viewer.close()
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()
    print("stopped", file=sys.stderr)
    return ExitCode.OK


if __name__ == "__main__":
    sys.exit(main())
