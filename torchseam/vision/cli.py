"""``torchseam detect``: TIPM feature point of single frames."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from torchseam.core.cliargs import out_dir_arg
from torchseam.core.config import JOINT_PROFILES, STRIPE_AXES, STRIPE_RESPONSES
from torchseam.core.errors import FrameError, TorchseamError

if TYPE_CHECKING:  # imported when the command runs: the parser (--help) needs no OpenCV
    import numpy as np

    from torchseam.core.orient import FrameView
    from torchseam.vision.profiles import ProfileFinder
    from torchseam.vision.tipm import Tipm, TipmResult


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "detect", help="find the weld feature point in frames (TIPM, clean frames)",
        description="Run TIPM on each frame and print 'FILE u v' or 'FILE none: <reason>'. "
                    "Frames may be colour or mono, 8 or 16 bit, of any size (the camera's "
                    "size matters for 3D, not for finding the corner). A file that cannot be "
                    "read is one error line on stderr and skipped; the others are still "
                    "detected: not a regular file (a FIFO, never opened), not an image, or "
                    "an image whose header declares more pixels than the limit (2**25, "
                    "$TORCHSEAM_MAX_FRAME_PIXELS; never decoded). Exit code 0 when a point "
                    "was found, 1 when none was, 2 when a file could not be read.")
    p.add_argument("frames", nargs="+", type=Path, metavar="FRAME",
                   help="image files (PNG, JPEG, TIFF, ...)")
    p.add_argument("--overlay", type=out_dir_arg, metavar="DIR",
                   help="write an overlay image per frame into DIR: the stripe's centre "
                        "line, the arm fits and the point found (default: none)")
    p.add_argument("--stripe-axis", choices=STRIPE_AXES, default="auto",
                   help="how the stripe runs in the image: along the rows, along the columns "
                        "(sensor mounted at 90 degrees), or auto: found per frame (default)")
    p.add_argument("--stripe-response", choices=STRIPE_RESPONSES, default="auto",
                   help="a colour image's stripe response: red (red excess), intensity (the "
                        "channels' mean: a stripe overexposed into white) or auto: per image "
                        "(default)")
    p.add_argument("--joint", choices=JOINT_PROFILES, default="fillet",
                   help="the joint profile to find (configs/profiles.yaml): fillet (the corner "
                        "of two stripe arms, TIPM; default), v_groove (shoulders, flanks, root "
                        "edges; aims at the root centre), butt (the gap in a straight stripe: "
                        "a break, a dip or a step; aims at its centre) or lap (the step edge; "
                        "aims at the root). Other than fillet, each line also gives the "
                        "feature points as NAME=U,V and the groove's width, root gap and "
                        "cross-section area in pixels where the profile has them")
    p.add_argument("--centre-line", choices=("subpixel", "thinning"), default="subpixel",
                   help="centre-line method (default subpixel; thinning as in the paper)")
    p.set_defaults(func=run)


def _detect(tipm: Tipm, img: np.ndarray, axis: str, response: str
            ) -> tuple[TipmResult, FrameView]:
    """TIPM on ``img`` in the view the settings give (auto: the one that finds a corner); the
    result's point is in the view's pixels."""
    import numpy as np

    from torchseam.core.orient import FrameView
    from torchseam.vision.tipm import find_view

    view = (find_view(img, tipm, axis, response)
            or FrameView("rows" if axis == "auto" else axis, img.shape[0],
                         "red" if response == "auto" else response))
    return tipm(np.ascontiguousarray(view.frame(img))), view


def _detect_profile(find: ProfileFinder | None, img: np.ndarray, path: Path,
                    args: argparse.Namespace, used: set[str]) -> bool:
    """One frame's joint profile (``--joint`` other than fillet): its line on stdout, its
    overlay; whether it was found. The view: ``--stripe-axis`` (auto: the way the stripe runs,
    :func:`~torchseam.vision.axis.stripe_axis`) and ``--stripe-response`` (auto: red)."""
    import cv2
    import numpy as np

    from torchseam.core.orient import FrameView
    from torchseam.vision.axis import stripe_axis
    from torchseam.vision.profiles import draw_profile

    assert find is not None
    resp = "red" if args.stripe_response == "auto" else args.stripe_response
    along = (stripe_axis(img, find.tipm, resp) or "rows") if args.stripe_axis == "auto" else (
        args.stripe_axis)
    view = FrameView(along, img.shape[0], resp)
    shown = np.ascontiguousarray(view.frame(img))
    res = find(shown)
    if res.ok:
        cam = res.to_camera(view)
        extra = [f"{k}={p[0]:.3f},{p[1]:.3f}" for k, p in cam.points.items()]
        extra += [f"{k}={x:.2f}" for k, x in (("width_px", res.width_px),
                                              ("gap_px", res.gap_px),
                                              ("area_px2", res.area_px2)) if np.isfinite(x)]
        print(f"{path} {cam.aim[0]:.3f} {cam.aim[1]:.3f} " + " ".join(extra))
    else:
        print(f"{path} none: {res.reason}")
    if args.overlay:
        out = draw_profile(shown, res)
        if view.turned:
            out = cv2.rotate(out, cv2.ROTATE_90_COUNTERCLOCKWISE)
        dest = args.overlay / _overlay_name(path, used)
        if not cv2.imwrite(str(dest), out):
            raise TorchseamError(f"--overlay: {dest}: cannot be written")
    return res.ok


def _overlay_name(path: Path, used: set[str]) -> str:
    """``STEM_tipm.png``, with the frame's position added when two inputs share a stem."""
    name = f"{path.stem}_tipm.png"
    k = 1
    while name in used:
        k += 1
        name = f"{path.stem}_{k}_tipm.png"
    used.add(name)
    return name


def run(args: argparse.Namespace) -> int:
    import cv2
    import numpy as np

    from torchseam.core.dataset import read_frame
    from torchseam.vision.profiles import ProfileFinder, load_profile_config
    from torchseam.vision.tipm import draw_overlay, load_tipm

    tipm = load_tipm(centre_line=args.centre_line)
    profile = (ProfileFinder(tipm, load_profile_config(), args.joint)
               if args.joint != "fillet" else None)
    if args.overlay:
        try:
            args.overlay.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise TorchseamError(f"--overlay {args.overlay}: cannot create the folder "
                                 f"({e.strerror})") from None
    found, unread, used = 0, 0, set[str]()
    for path in args.frames:
        try:
            img = read_frame(path)
        except FrameError as e:  # bad input: one line, the other frames still detected
            print(f"torchseam detect: error: {e}", file=sys.stderr, flush=True)
            unread += 1
            continue
        if args.joint != "fillet":
            found += _detect_profile(profile, img, path, args, used)
            continue
        res, axis = _detect(tipm, img, args.stripe_axis, args.stripe_response)
        uv = axis.to_camera(res.uv)
        found += res.ok
        print(f"{path} {uv[0]:.3f} {uv[1]:.3f}" if res.ok else f"{path} none: {res.reason}")
        if args.overlay:
            shown = draw_overlay(np.ascontiguousarray(axis.frame(img)), res)
            if axis.turned:
                shown = cv2.rotate(shown, cv2.ROTATE_90_COUNTERCLOCKWISE)
            dest = args.overlay / _overlay_name(path, used)
            if not cv2.imwrite(str(dest), shown):
                raise TorchseamError(f"--overlay: {dest}: cannot be written")
    # exit 2 when a file could not be read (bad input), 1 when no frame gave a point
    return 2 if unread else 0 if found else 1
