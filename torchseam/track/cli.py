"""``torchseam track`` and ``torchseam eval``: follow the feature point through a frame folder."""

from __future__ import annotations

import argparse
import contextlib
import csv
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from torchseam.core.cliargs import model_arg, out_file_arg, threads_arg
from torchseam.core.config import JOINT_PROFILES, STRIPE_AXES, STRIPE_RESPONSES
from torchseam.core.errors import FrameError, TorchseamError
from torchseam.core.report import error_stats, format_table, percentiles_ms
from torchseam.track.names import TRACKERS

if TYPE_CHECKING:  # imported when the command runs: the parser (--help) needs no torch
    from torchseam.core.dataset import Dataset
    from torchseam.core.orient import FrameView
    from torchseam.vision.tipm import Tipm

MISSING = "missing"  # track.csv status of a frame number the folder has no image for
#: track.csv status of a frame that cannot be decoded or is not the size of the folder's
#: first frame (the tracker skips it and goes on with the next one); a name that is not a
#: regular file (a FIFO: never opened) or an image above the pixel limit (never decoded) too
#: (:mod:`torchseam.core.imageio`)
UNREADABLE = "unreadable"
#: ``eval``: a frame said ``tracked`` farther than this from its label is a false one (px; the
#: benchmarks' rule, bench/tracking.py)
FALSE_TRACKED_PX = 5.0
#: unreadable frames named one by one on stderr; the rest are counted
WARN_FRAMES = 10


def _parse_init(text: str | None) -> np.ndarray | None:
    if text is None:
        return None
    try:
        u, v = (float(x) for x in text.split(","))
    except ValueError:
        raise TorchseamError(f"--init {text!r}: expected U,V (two numbers)") from None
    if not (np.isfinite(u) and np.isfinite(v)):
        raise TorchseamError(f"--init {text!r}: U and V must be finite")
    return np.array([u, v])


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("frames_dir", type=Path, metavar="FRAMES_DIR",
                   help="folder of NNNNN.png frames (the dataset format)")
    p.add_argument("--tracker", choices=TRACKERS, default="anchored",
                   help="tracker (default anchored: EAKF-STC fused with TIPM, as the live loop "
                        "and demo run it; eakf-stc alone drifts along the stripe)")
    p.add_argument("--joint", choices=JOINT_PROFILES, default=None,
                   help="the joint in the frames (default: the part's joint that the folder's "
                        "meta.json names, as `torchseam simulate` writes it, else fillet; "
                        "fillet: --tracker follows TIPM's corner; v_groove, butt, lap: the "
                        "profile's aim point, configs/profiles.yaml, with the default tracker)")
    p.add_argument("--init", metavar="U,V",
                   help="start point on the first frame (default: TIPM on the first frame; a "
                        "--joint other than fillet: its profile's aim point there)")
    p.add_argument("--stripe-axis", choices=STRIPE_AXES, default="auto",
                   help="how the stripe runs in the frames: rows, columns (sensor mounted at "
                        "90 degrees) or auto: found on the first frame (default)")
    p.add_argument("--stripe-response", choices=STRIPE_RESPONSES, default="auto",
                   help="a colour stream's stripe response: red (red excess), intensity (the "
                        "channels' mean: a stripe overexposed into white) or auto: chosen on the "
                        "first frame (default)")
    p.add_argument("--threads", type=threads_arg, default=1, metavar="N",
                   help="torch and OpenCV threads (default 1: the live loop's setting)")
    p.add_argument("--model", type=model_arg, default=None, metavar="FILE",
                   help="tracker model file for the anchored and eakf-stc trackers, e.g. a "
                        "run's runs/NAME/live_tracker.safetensors (default "
                        "models/live_tracker.safetensors)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "track", help="track the feature point through a folder of frames",
        description="Track the weld feature point through FRAMES_DIR (frames in file-name "
                    "order; labels.csv is not read) and write frame,u,v,status per frame "
                    "number as it goes (status tracked, coasting, lost; unreadable for a frame "
                    "that cannot be decoded, is not the size of the first one, is not a "
                    "regular file (a FIFO: never opened) or declares more pixels than the "
                    "limit (2**25, $TORCHSEAM_MAX_FRAME_PIXELS: never decoded), which the "
                    "tracker skips; missing for a number the folder has no image for).")
    _common(p)
    p.add_argument("--out", type=out_file_arg, default=Path("track.csv"),
                   help="output CSV, written row by row (default track.csv)")
    p.set_defaults(func=run_track)
    e = sub.add_parser(
        "eval", help="track a labelled folder and print the error table",
        description="Track FRAMES_DIR and compare with its labels.csv: RMSE, max error, "
                    "% frames > 5 px, % lost (> 15 px or no point), % of frames said tracked "
                    "and how many of those are more than 5 px off (false trk; the start frame "
                    "counts in neither), ms per frame (frame -> "
                    "point; the tracker's learning between frames, as the live loop runs it, "
                    "is not counted). A frame that cannot be read (as for track) counts as "
                    "lost.")
    _common(e)
    e.set_defaults(func=run_eval)


def _resolve_joint(args: argparse.Namespace, ds: Dataset) -> str:
    """``args.joint`` from ``--joint`` or the folder's meta.json (:meth:`Dataset.joint`; a
    warning on stderr when they disagree). Returns a note for the summary line: '' or where
    the joint came from."""
    args.joint, origin, warning = ds.joint(args.joint)
    if warning:
        print(warning, file=sys.stderr, flush=True)
    return f"joint {args.joint} from {origin}; " if origin else ""


def _start(img: np.ndarray, tipm: Tipm, uv0: np.ndarray | None, args: argparse.Namespace,
           name: str, number: int) -> tuple[FrameView, np.ndarray, str]:
    """How to view the stream and where to start, from its first readable frame ``img``
    (as :func:`~torchseam.track.peers.run_tracker` starts)."""
    from torchseam.core.orient import FrameView
    from torchseam.vision.tipm import find_view

    axis, response = args.stripe_axis, args.stripe_response
    if args.joint != "fillet":  # a profile: the stripe's own axis, the profile's aim point
        from torchseam.track.profile import profile_start
        return profile_start(img, tipm, args.joint, uv0, axis, response, name, number)
    if "auto" in (axis, response):
        view = find_view(img, tipm, axis, response)
        if view is None:
            raise TorchseamError(f"{name}: no stripe corner on the first frame (stripe axis "
                                 f"{axis}, response {response}); give --stripe-axis and "
                                 "--stripe-response, or --joint for a joint that is not a "
                                 "fillet (v_groove, butt, lap)")
    else:
        view = FrameView(axis, img.shape[0], response)
    if uv0 is not None:
        return view, np.asarray(uv0, float), "given"
    res = tipm(view.frame(img))
    if not res.ok:
        raise TorchseamError(f"{name}: TIPM cannot start the tracker on the first frame "
                             f"({res.reason}); give the start point with --init U,V")
    return view, view.to_camera(res.uv), f"TIPM on frame {number}"


def _make_tracker(args: argparse.Namespace, tipm: Tipm):
    """The tracker ``--tracker`` names, with ``--model``'s parameters (checked here, before
    any output is written)."""
    import cv2
    import torch

    from torchseam.track.peers import make_tracker

    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    if args.joint != "fillet":
        from torchseam.track.profile import load_profile_track_config, make_joint_tracker
        from torchseam.vision.profiles import load_profile_config
        return make_joint_tracker(args.tracker, args.joint, tipm, load_profile_config(),
                                  load_profile_track_config(), args.model)
    return make_tracker(args.tracker, tipm, model_path=args.model)


def _follow(args: argparse.Namespace, tracker, ds: Dataset, uv0: np.ndarray | None,
            on_frame: Callable[[int, np.ndarray, str], None], tipm: Tipm
            ) -> tuple[str, list[float]]:
    """Track ``ds`` frame by frame with ``tracker`` as the live loop drives it (``update``,
    then its ``idle``), calling ``on_frame(position, uv, status name)`` for each frame in
    order.

    A frame that cannot be decoded or is not the size of the first readable one is reported
    ``unreadable`` (NaN point, a warning on stderr) and skipped: the tracker goes on with the
    next frame. The tracker starts on the first readable frame (``tipm``: the start point
    without ``--init``, the view with ``auto``).

    Returns:
        ``(start note, seconds of each update)``.
    """
    from tqdm import tqdm

    from torchseam.track.fusion import TrackStatus
    from torchseam.track.peers import STATUS_NAMES

    idle = getattr(tracker, "idle", None)
    view: FrameView | None = None
    size: tuple[int, ...] = ()
    note, secs, bad = "", [], 0
    nan = np.full(2, np.nan)
    bar = tqdm(total=len(ds), desc=f"{args.tracker} {ds.root.name}", unit="frame", leave=False)
    try:
        for i in range(len(ds)):
            bar.update(1)
            try:
                img = ds.read(i)
                if size and img.shape[:2] != size:
                    raise FrameError(f"{ds.paths[i]}: frame is {img.shape[1]} x {img.shape[0]} "
                                     f"px, the folder's frames are {size[1]} x {size[0]}")
            except FrameError as e:
                bad += 1
                if bad <= WARN_FRAMES:
                    tqdm.write(f"warning: {e}: marked {UNREADABLE}, skipped", file=sys.stderr)
                on_frame(i, nan, UNREADABLE)
                continue
            if view is None:
                view, uv0, note = _start(img, tipm, uv0, args, str(ds.paths[i]),
                                         int(ds.frames[i]))
                size = img.shape[:2]
                tracker.init(view.frame(img), view.to_canonical(uv0))
                on_frame(i, uv0, STATUS_NAMES[int(TrackStatus.TRACKED)])
                continue
            t0 = time.perf_counter()
            uv, st = tracker.update(view.frame(img))
            uv = view.to_camera(uv)
            secs.append(time.perf_counter() - t0)
            if idle is not None:
                idle()
            on_frame(i, np.asarray(uv, float), STATUS_NAMES[int(st)])
    finally:
        bar.close()
    if bad > WARN_FRAMES:
        print(f"warning: {ds.root}: {bad} frames in all marked {UNREADABLE}", file=sys.stderr)
    if view is None:
        raise TorchseamError(f"{ds.root}: no readable frame to start on")
    return note, secs


def _warn_missing(ds: Dataset) -> np.ndarray:
    """Say which frame numbers the folder lacks (the trackers take the frames on both sides
    of a gap as consecutive, so their motion model is off there); returns them."""
    gone = ds.missing
    if len(gone):
        shown = ", ".join(str(int(f)) for f in gone[:10]) + (" ..." if len(gone) > 10 else "")
        print(f"warning: {ds.root}: {len(gone)} frame number(s) missing ({shown}); the tracker "
              "takes the frames around a gap as consecutive", file=sys.stderr)
    return gone


def run_track(args: argparse.Namespace) -> int:
    from torchseam.core.dataset import Dataset
    from torchseam.track.peers import STATUS_NAMES
    from torchseam.vision.tipm import load_tipm

    uv0 = _parse_init(args.init)
    ds = Dataset.open(args.frames_dir, labels=False)  # track needs no labels
    said = _resolve_joint(args, ds)
    gone = {int(f) for f in _warn_missing(ds)}
    tipm = load_tipm()
    tracker = _make_tracker(args, tipm)
    counts = dict.fromkeys([*STATUS_NAMES.values(), UNREADABLE, MISSING], 0)
    state = {"next": int(ds.frames[0])}
    with contextlib.ExitStack() as stack:
        out: list = []  # [file, csv writer] once the first row is due

        def row(i: int, uv: np.ndarray, status: str) -> None:
            if not out:
                fh = stack.enter_context(args.out.open("w", newline=""))
                out[:] = [fh, csv.writer(fh)]
                out[1].writerow(["frame", "u", "v", "status"])
            fh, w = out
            f = int(ds.frames[i])
            for g in range(state["next"], f):  # one row per frame number, none dropped
                if g in gone:
                    w.writerow([g, "", "", MISSING])
                    counts[MISSING] += 1
            state["next"] = f + 1
            ok = bool(np.all(np.isfinite(uv)))
            w.writerow([f, f"{uv[0]:.3f}" if ok else "", f"{uv[1]:.3f}" if ok else "", status])
            counts[status] = counts.get(status, 0) + 1
            fh.flush()  # a run that stops early keeps the rows so far

        try:
            note, _ = _follow(args, tracker, ds, uv0, row, tipm)
        except KeyboardInterrupt:
            # the rows written stay (flushed one by one): say how far they go, then stop
            done = sum(n for k, n in counts.items() if k != MISSING)
            kept = (f"{args.out} holds frames {int(ds.frames[0])}-{state['next'] - 1}"
                    if out else f"nothing written to {args.out}")
            print(f"{args.tracker}: interrupted after {done} of {len(ds)} frames; {kept}",
                  file=sys.stderr, flush=True)
            raise
    shown = ", ".join(f"{k} {n}" for k, n in counts.items()
                      if n or k in STATUS_NAMES.values())
    print(f"{args.tracker}: {len(ds)} frames -> {args.out} ({said}start: {note}; {shown})")
    return 0


def run_eval(args: argparse.Namespace) -> int:
    from torchseam.core.dataset import Dataset
    from torchseam.vision.tipm import load_tipm

    uv0 = _parse_init(args.init)
    ds = Dataset.open(args.frames_dir, require_labels=True)
    said = _resolve_joint(args, ds)
    _warn_missing(ds)
    uv = np.full((len(ds), 2), np.nan)
    said_tracked = np.zeros(len(ds), bool)
    start = np.zeros(len(ds), bool)  # the frame the tracker started on (its point is given)
    n_bad = 0

    done = np.zeros(len(ds), bool)

    def keep(i: int, p: np.ndarray, status: str) -> None:
        nonlocal n_bad
        uv[i] = p
        said_tracked[i] = status == "tracked"
        start[i] = not start.any() and status != UNREADABLE
        n_bad += status == UNREADABLE
        done[i] = True

    tipm = load_tipm()
    try:
        note, secs = _follow(args, _make_tracker(args, tipm), ds, uv0, keep, tipm)
    except KeyboardInterrupt:
        # the table of the frames tracked so far, said to be partial; then stop (exit 130)
        print(f"{args.tracker}: interrupted after {int(done.sum())} of {len(ds)} frames; the "
              "table is theirs (times not kept)", file=sys.stderr, flush=True)
        _eval_table(args, ds, uv, said_tracked, start, done, n_bad, said, "interrupted", [])
        raise
    _eval_table(args, ds, uv, said_tracked, start, done, n_bad, said, note, secs)
    return 0


def _eval_table(args: argparse.Namespace, ds: Dataset, uv: np.ndarray,
                said_tracked: np.ndarray, start: np.ndarray, done: np.ndarray, n_bad: int,
                said: str, note: str, secs: list[float]) -> None:
    """``eval``'s table over the labelled frames tracked (``done``)."""
    labelled = ds.labelled & done
    err = np.linalg.norm(uv - ds.labels, axis=1)[labelled]
    s = error_stats(err)
    # the status against the labels: a frame said tracked more than FALSE_TRACKED_PX off is a
    # false one (the start frame is not counted)
    counted = ~start[labelled]
    tracked = said_tracked[labelled][counted]
    false = int(np.sum(tracked & ~(err[counted] <= FALSE_TRACKED_PX)))
    pct_tracked = 100.0 * float(tracked.mean()) if len(tracked) else 0.0
    p50, p99 = percentiles_ms(secs) if secs else ("-", "-")
    print(f"{args.tracker} on {ds.root} ({int(labelled.sum())} of {len(ds)} frames labelled; "
          f"{said}start: {note}" + (f"; {n_bad} unreadable, counted lost" if n_bad else "") + ")")
    print(format_table(["tracker", "frames", "RMSE px", "max px", "> 5 px %", "lost %",
                        "tracked %", "false trk", "ms p50", "ms p99"],
                       [[args.tracker, s["n"], s["rmse"], s["max"], s["pct_gt5"], s["pct_lost"],
                         pct_tracked, false, p50, p99]]))
