"""Joint profiles (torchseam/vision/profiles.py) and the stripe axis from the stripe
(torchseam/vision/axis.py): a real V-groove frame against hand-measured reference points, and
drawn frames of every profile whose feature points are known exactly."""

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.special import erf

from torchseam.core.config import ConfigError, load_config
from torchseam.core.orient import BRIGHTNESS
from torchseam.vision.axis import stripe_axis
from torchseam.vision.profiles import (
    JOINTS,
    LAP_DARK_FACE,
    ProfileConfig,
    ProfileFinder,
    draw_profile,
    fit_line,
    groove_area,
    load_profile_config,
)
from torchseam.vision.tipm import find_view, load_tipm

REAL = Path(__file__).parent / "data" / "real"
TIPM = load_tipm()
CFG = load_profile_config()


def finder(joint: str) -> ProfileFinder:
    return ProfileFinder(TIPM, CFG, joint)


# --------------------------------------------------------------------------- the real frame
#: Reference feature points of tests/data/real/v_groove_spatter.png (u, v), measured without
#: the code under test:
#: - shoulders: the stripe's centre was taken per column as the intensity centroid of the
#:   pixels within 8 rows of a line drawn by eye through each straight piece (zoomed crops of
#:   the image, 8x, with a 5 px grid), background (the median of 40 rows around) subtracted;
#:   straight lines were fitted (np.polyfit) to the left plate (columns 20-480), the left flank
#:   (545-715), the right flank (845-1015) and the right plate (1075-1270), column ranges
#:   picked by eye well away from the bends; the shoulders are where plate and flank lines
#:   cross (the fits' residuals: 0.44, 0.71, 0.37, 0.33 px).
#: - root edges: where the lit stripe ends at the root gap, read off printed grey values of the
#:   pixels around each end: the column where the brightness along the flank's last row falls
#:   to half its peak (left: row 585, 223 at column 735, 165 at 736, 83 at 737 -> 736.6; right:
#:   row 586, 121 at column 815, 170 at 816, 226 at 817, peak 255 -> 815.3), the row of the
#:   stripe's last cross-section there.
REAL_REFERENCE = {
    "left_shoulder": (518.6, 385.2),
    "left_root": (736.6, 585.0),
    "right_root": (815.3, 585.8),
    "right_shoulder": (1037.6, 393.4),
}


def test_real_v_groove_frame_feature_points_within_3px():
    img = cv2.imread(str(REAL / "v_groove_spatter.png"), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.shape == (1000, 1280)
    res = finder("v_groove")(img)
    assert res.ok, res.reason
    for name, ref in REAL_REFERENCE.items():
        err = float(np.hypot(*(res.points[name] - np.array(ref))))
        assert err <= 3.0, f"{name}: {res.points[name]} is {err:.1f} px from {ref}"
    mid = (np.array(REAL_REFERENCE["left_root"]) + REAL_REFERENCE["right_root"]) / 2
    assert np.hypot(*(res.aim - mid)) <= 3.0
    ref_gap = np.hypot(*np.subtract(REAL_REFERENCE["right_root"], REAL_REFERENCE["left_root"]))
    assert abs(res.gap_px - ref_gap) <= 4.0
    ref_area = groove_area(np.array(list(REAL_REFERENCE.values())))
    assert abs(res.area_px2 - ref_area) <= 0.03 * ref_area
    # the stripe runs along the rows there, and turned a quarter along the columns
    assert stripe_axis(img, TIPM) == "rows"
    assert stripe_axis(cv2.rotate(img, cv2.ROTATE_90_CLOCKWISE), TIPM) == "columns"


def test_real_frame_licence_travels_with_it():
    lic = (REAL / "LICENSE-douglas125-LaserLineTracking").read_text()
    assert "MIT License" in lic and "Douglas Coimbra de Andrade" in lic


# --------------------------------------------------------------------------- drawn frames
def draw(pieces, size=(480, 640), sigma=1.3, seed=0, blobs=(), edge_rows=None):
    """A mono uint8 frame (H, W) of straight stripe pieces ``(p0, p1, peak)`` with a Gaussian
    cross-section of ``sigma``, read noise, speckle and optional spatter blobs ``(u, v, r)``
    and a bright plate from row ``edge_rows`` down (a table or part edge beside the stripe)."""
    h, w = size
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(float)
    img = np.zeros(size)
    for (x0, y0), (x1, y1), peak in pieces:
        # a lit straight piece seen through a Gaussian blur: across, a Gaussian; along, a step
        # at each end (half the light at the end itself), so pieces that meet add up to one
        d = np.array([x1 - x0, y1 - y0], float)
        n = np.hypot(*d)
        e = d / n
        t = (x - x0) * e[0] + (y - y0) * e[1]
        across = (x - x0) * -e[1] + (y - y0) * e[0]
        along = 0.5 * (erf(t / (np.sqrt(2) * sigma)) - erf((t - n) / (np.sqrt(2) * sigma)))
        img += peak * np.exp(-across**2 / (2 * sigma**2)) * along
    speckle = cv2.resize(rng.uniform(0.75, 1.25, (h // 3 + 1, w // 3 + 1)), (w, h))
    img *= speckle
    for u, v, r in blobs:
        img = np.maximum(img, 230 * np.exp(-((x - u) ** 2 + (y - v) ** 2) / (2 * r**2)))
    if edge_rows is not None:
        img[edge_rows:] += 90
    img += 8 + rng.normal(0, 2.5, size)
    return np.clip(img, 0, 255).astype(np.uint8)


def near(res, truth, tol):
    for name, p in truth.items():
        err = float(np.hypot(*(res.points[name] - np.asarray(p, float))))
        assert err <= tol, f"{name}: {res.points[name]} is {err:.2f} px from {p}"


V_TRUTH = {"left_shoulder": (200.0, 150.0), "left_root": (300.0, 250.0),
           "right_root": (330.0, 250.0), "right_shoulder": (430.0, 150.0)}


@pytest.mark.parametrize("seed", [0, 1])
def test_v_groove_with_root_gap_and_spatter(seed):
    t = V_TRUTH
    pieces = [((0, 150), t["left_shoulder"], 200), (t["left_shoulder"], t["left_root"], 110),
              (t["right_root"], t["right_shoulder"], 110), (t["right_shoulder"], (639, 150), 200)]
    img = draw(pieces, seed=seed, blobs=[(380, 60, 4), (250, 330, 5), (90, 260, 3)])
    res = finder("v_groove")(img)
    assert res.ok and res.reason == "", res.status
    near(res, t, 1.0)
    assert np.hypot(*(res.aim - (315.0, 250.0))) <= 1.0
    assert res.width_px == pytest.approx(230.0, abs=1.5)
    assert res.gap_px == pytest.approx(30.0, abs=2.0)
    assert res.area_px2 == pytest.approx(groove_area(np.array(list(t.values()))), rel=0.03)


def test_v_groove_closed_root_and_single_bevel():
    closed = [((0, 150), (200, 150), 200), ((200, 150), (300, 260), 110),
              ((300, 260), (400, 150), 110), ((400, 150), (639, 150), 200)]
    res = finder("v_groove")(draw(closed))
    assert res.ok, res.status
    near(res, {"left_root": (300, 260), "right_root": (300, 260),
               "left_shoulder": (200, 150), "right_shoulder": (400, 150)}, 1.5)
    assert res.gap_px == pytest.approx(0.0, abs=1e-6)
    # a bevelled branch over a plate seen from the side: the plate's stripe runs straight into
    # the root gap; the other side has a flank and a shoulder
    single = [((0, 300), (300, 300), 200), ((320, 290), (400, 190), 110),
              ((400, 190), (639, 120), 200)]
    res = finder("v_groove")(draw(single))
    assert res.ok and res.reason == "single bevel", res.status
    near(res, {"left_root": (300, 300), "left_shoulder": (300, 300),
               "right_root": (320, 290), "right_shoulder": (400, 190)}, 1.5)


def _v_groove_under_glare(seed: int, peak: float) -> np.ndarray:
    """The groove of :data:`V_TRUTH` (mono) under the arc's glare: a round glow (sigma 30 px,
    ``peak`` grey levels, clipped) at the root's height, lifting the light round the root
    edges towards clipping (the stripe on it clips: 255 at most)."""
    t = V_TRUTH
    pieces = [((0, 150), t["left_shoulder"], 200), (t["left_shoulder"], t["left_root"], 110),
              (t["right_root"], t["right_shoulder"], 110), (t["right_shoulder"], (639, 150), 200)]
    y, x = np.mgrid[0:480, 0:640].astype(float)
    glow = peak * np.exp(-((x - 315.0) ** 2 + (y - 255.0) ** 2) / (2 * 30.0**2))
    return np.clip(draw(pieces, seed=seed) + glow, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("seed", [0, 1])
def test_v_groove_root_edges_under_glare_that_lifts_the_light_towards_clipping(seed):
    """Glare round the root leaves the stripe little room to rise above it before clipping:
    its last lit pixels there read dim, and the root edges were put where the response fell
    below half the flank's median, short of the root (4.2-4.4 px each, the aim 3.0-3.1 px
    off); the level is now half the room the frame leaves there where that is less
    (profiles.headroom)."""
    res = finder("v_groove")(_v_groove_under_glare(seed, 240.0))
    assert res.ok and res.reason == "", res.status
    near(res, {k: V_TRUTH[k] for k in ("left_root", "right_root")}, 2.0)
    assert np.hypot(*(res.aim - (315.0, 250.0))) <= 1.5, res.aim


def test_a_groove_white_along_its_centre_line_is_read_by_its_brightness():
    """A colour groove whose stripe saturates R and G in its core (a wide stripe under the arc)
    has no red excess on its centre line: no level to end it by, so its red excess gives no
    groove (its ends were followed on over the root gap, or into the glare beside it) and its
    brightness reads it (this drawn stripe clips past its ends: they read 3-4 px on into the
    gap, alike, the aim below the root by less)."""
    t = V_TRUTH
    pieces = [((0, 150), t["left_shoulder"], 200), (t["left_shoulder"], t["left_root"], 200),
              (t["right_root"], t["right_shoulder"], 200), (t["right_shoulder"], (639, 150), 200)]
    core = draw(pieces, sigma=3.5, seed=0) / 200.0   # as _saturated_butt's, along the groove
    img = np.clip(np.stack([np.full_like(core, 40.0), 90.0 + 330.0 * core,
                            140.0 + 420.0 * core], axis=2), 0, 255).astype(np.uint8)
    red = finder("v_groove")._profile(img)
    assert not red.ok and "no red excess" in red.reason, red.status
    res = finder("v_groove")(img)
    assert res.ok, res.status
    assert np.hypot(*(res.aim - (315.0, 250.0))) <= 3.0, res.aim


def _v_groove_under_fume(seed: int) -> np.ndarray:
    """The groove of :data:`V_TRUTH` (mono) under a fume veil: its stripe soft (sigma 3.5 px,
    8-10 px wide) and 28 grey levels above a veil of 183, with read noise of 6 grey levels on
    the veil (the threshold's noise term, 3 times the ridge's 90th percentile, stands above
    the stripe's ridge on most of its pixels) and two spatter streaks at 255, one across the
    left flank near the root, one by the right root (as the bench's `smoke` extreme frames)."""
    t = V_TRUTH
    pieces = [((0, 150), t["left_shoulder"], 28.0), (t["left_shoulder"], t["left_root"], 28.0),
              (t["right_root"], t["right_shoulder"], 28.0),
              (t["right_shoulder"], (639, 150), 28.0)]
    rng = np.random.default_rng(seed + 10)
    img = draw(pieces, sigma=3.5, seed=seed) + 175.0 + rng.normal(0.0, 6.0, (480, 640))
    streaks = np.zeros((480, 640), np.uint8)
    for a, b in (((240, 230), (275, 165)), ((380, 215), (420, 250))):
        cv2.line(streaks, a, b, 255, 2, cv2.LINE_AA)
    return np.clip(np.maximum(img, streaks), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("seed", [2, 3, 5])
@pytest.mark.parametrize("look", ["mono", "colour"])
def test_a_groove_under_fume_is_read_on_its_brightness_blurred(seed, look):
    """Fume veils the stripe: the read noise on the veil sets the threshold above most of the
    stripe's ridge, its mask breaks into pieces and no groove is read (no shoulder on either
    side); blurred by ``soft_sigma_px`` the noise falls several times, the soft stripe keeps
    its ridge, and the groove is read (profiles.ProfileFinder._soft). A grey veil over a grey
    stripe has no red excess: a colour frame is read by its brightness, as a mono one."""
    img = _v_groove_under_fume(seed)
    if look == "colour":
        img = np.ascontiguousarray(np.repeat(img[..., None], 3, axis=2))
    plain = finder("v_groove")
    grey = cv2.transform(img, BRIGHTNESS) if look == "colour" else img
    assert not plain._profile(grey).ok   # the brightness as it is: no groove
    res = finder("v_groove")(img)
    assert res.ok, res.status
    near(res, V_TRUTH, 2.0)
    assert np.hypot(*(res.aim - (315.0, 250.0))) <= 1.5, res.aim
    off = dataclasses.replace(CFG, soft_sigma_px=0.0)   # without the blurred look: none
    assert not ProfileFinder(TIPM, off, "v_groove")(img).ok


def test_profiles_refuse_a_plain_straight_stripe():
    img = draw([((0, 200), (639, 210), 200)])
    for joint in ("v_groove", "butt", "lap"):
        res = finder(joint)(img)
        assert not res.ok and res.status.startswith("none: no "), (joint, res.status)
        assert np.all(np.isnan(res.aim))
    assert not finder("fillet")(img).ok


@pytest.mark.parametrize("how", ["break", "dip", "step"])
def test_butt_gap_centre_and_width(how):
    if how == "break":
        pieces = [((0, 240), (300, 244), 200), ((318, 244.3), (639, 248), 200)]
        centre, width = (309.0, 244.15), 18.0
    elif how == "dip":
        pieces = [((0, 240), (300, 244), 200), ((300, 244), (312, 244.2), 40),
                  ((312, 244.2), (639, 248), 200)]
        centre, width = (306.0, 244.1), 12.0
    else:  # flush, one plate 8 px higher in the view (hi-lo)
        pieces = [((0, 240), (305, 244), 200), ((305, 236), (639, 240), 200)]
        centre, width = (305.0, 240.0), 0.0
    res = finder("butt")(draw(pieces, blobs=[(500, 100, 4)]))
    assert res.ok and res.reason == how, res.status
    assert abs(res.aim[0] - centre[0]) <= 1.5 and abs(res.aim[1] - centre[1]) <= 4.5
    assert res.width_px == pytest.approx(width, abs=2.0 if width else 3.0)


@pytest.mark.parametrize("far_side", ["down", "up"])
def test_lap_edge_and_root(far_side):
    # two plates' stripes, the step at u = 330, the near plate's edge face dark: which end is
    # the root (the far plate's) follows the sensor's far side
    pieces = [((0, 200), (330, 204), 200), ((331, 236), (639, 240), 200)]
    cfg = dataclasses.replace(CFG, far_side=far_side)
    res = ProfileFinder(TIPM, cfg, "lap")(draw(pieces))
    assert res.ok, res.status
    upper, lower = (330, 204), (331, 236)
    near(res, {"edge": upper, "root": lower} if far_side == "down"
         else {"edge": lower, "root": upper}, 1.5)
    np.testing.assert_allclose(res.aim, res.points["root"])
    assert res.width_px == pytest.approx(32.0, abs=1.0)
    assert res.reason == LAP_DARK_FACE   # its two ends read apart (the tracker may put one back)


def _lap_z(angle_deg: float) -> tuple[list, np.ndarray, np.ndarray]:
    """A lap whose edge face is lit: the far plate's stripe, the face, the near plate's, the
    whole stripe turned by ``angle_deg`` about (320, 240) (a sensor tilted to the joint); the
    root (the far plate's end, upper in the view) and the edge (the near plate's end)."""
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))

    def turn(p):
        x, y = p[0] - 320.0, p[1] - 240.0
        return (320.0 + c * x - s * y, 240.0 + s * x + c * y)

    root, edge = (300.0, 230.0), (330.0, 262.0)   # the face: 30 px along, 32 down
    pieces = [(turn((0.0, 230.0)), turn(root), 200), (turn(root), turn(edge), 120),
              (turn(edge), turn((639.0, 262.0)), 200)]
    return pieces, np.array(turn(root)), np.array(turn(edge))


@pytest.mark.parametrize("angle_deg", [0.0, -30.0, 25.0])
def test_lap_with_a_lit_edge_face_across_the_view(angle_deg):
    """The stripe runs down the lit edge face (a Z), across the view at a slope: the root and
    the edge are where the face's line meets the plates' (the stripe's own direction, not the
    rows, tells the plates' offset)."""
    pieces, root, edge = _lap_z(angle_deg)
    res = finder("lap")(draw(pieces))
    assert res.ok, res.status
    assert np.linalg.norm(res.points["root"] - root) <= 1.5, res.points
    assert np.linalg.norm(res.points["edge"] - edge) <= 1.5, res.points
    np.testing.assert_allclose(res.aim, res.points["root"])
    assert res.reason == ""   # not LAP_DARK_FACE: both ends are on the face's line


def test_a_bright_edge_beside_the_stripe_is_no_part_of_it():
    """A butt gap in a stripe with a bright plate edge 25 rows below it, along it: the gap is
    found where it is, and the stripe axis is the stripe's."""
    pieces = [((0, 200), (300, 203), 200), ((318, 203.2), (639, 206), 200)]
    img = draw(pieces, edge_rows=228)
    res = finder("butt")(img)
    assert res.ok, res.status
    assert abs(res.aim[0] - 309.0) <= 1.5 and abs(res.aim[1] - 203.1) <= 1.5
    assert np.all(np.abs(res.centre[:, 1] - 203) < 6), "the edge was read as stripe"
    assert stripe_axis(img, TIPM) == "rows"


def test_auto_axis_follows_the_stripe_not_a_corner():
    """A butt stripe running down the columns has no corner in either view: auto still says
    columns (the old rule, the view that yields a corner, had nothing to go by), and a
    V-groove turned a quarter is read in the turned view."""
    butt = draw([((0, 240), (300, 244), 200), ((318, 244.3), (639, 248), 200)])
    turned = cv2.rotate(butt, cv2.ROTATE_90_CLOCKWISE)
    assert stripe_axis(butt, TIPM) == "rows"
    assert stripe_axis(turned, TIPM) == "columns"
    t = V_TRUTH
    v = draw([((0, 150), t["left_shoulder"], 200), (t["left_shoulder"], t["left_root"], 110),
              (t["right_root"], t["right_shoulder"], 110), (t["right_shoulder"], (639, 150), 200)])
    view = find_view(cv2.rotate(v, cv2.ROTATE_90_COUNTERCLOCKWISE), TIPM, "auto", "auto")
    assert view is None or view.axis == "columns"


def test_fillet_is_tipm_corner():
    img = draw([((0, 100), (320, 300), 200), ((320, 300), (639, 120), 200)])
    res = finder("fillet")(img)
    tip = TIPM(img)
    assert res.ok and tip.ok
    np.testing.assert_allclose(res.aim, tip.uv)
    assert np.hypot(*(res.aim - (320, 300))) < 1.0
    assert set(res.points) == {"corner"}


def test_profile_names_and_config_errors(tmp_path):
    assert JOINTS == ("fillet", "v_groove", "butt", "lap")
    with pytest.raises(ValueError, match="joint 'tee'"):
        ProfileFinder(TIPM, CFG, "tee")
    bad = tmp_path / "profiles.yaml"
    text = (Path(__file__).parents[1] / "configs" / "profiles.yaml").read_text()
    bad.write_text(text.replace("min_gap_px: 6.0", "min_gap_px: -1"))
    with pytest.raises(ConfigError, match="min_gap_px"):
        load_config(ProfileConfig, bad)


def test_overlay_draws_points(tmp_path):
    t = V_TRUTH
    img = draw([((0, 150), t["left_shoulder"], 200), (t["left_shoulder"], t["left_root"], 110),
                (t["right_root"], t["right_shoulder"], 110),
                (t["right_shoulder"], (639, 150), 200)])
    res = finder("v_groove")(img)
    out = draw_profile(img, res)
    assert out.shape == img.shape + (3,)
    u, v = np.rint(res.aim).astype(int)
    assert np.abs(out[v, u].astype(int) - [0, 255, 255]).max() <= 8


def test_detect_joint_on_the_real_frame_and_turned(tmp_path, capsys):
    """``torchseam detect --joint v_groove``: the aim point and the feature points in camera
    pixels, the same on the frame turned a quarter (auto axis: the stripe's own)."""
    from torchseam.cli import main

    img = cv2.imread(str(REAL / "v_groove_spatter.png"), cv2.IMREAD_UNCHANGED)
    turned = tmp_path / "turned.png"
    cv2.imwrite(str(turned), cv2.rotate(img, cv2.ROTATE_90_COUNTERCLOCKWISE))
    assert main(["detect", "--joint", "v_groove", str(REAL / "v_groove_spatter.png"),
                 str(turned), "--overlay", str(tmp_path / "ov")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2 and len(list((tmp_path / "ov").iterdir())) == 2
    w = img.shape[1]
    for line, to_cam in ((lines[0], lambda p: p), (lines[1], lambda p: (w - 1 - p[1], p[0]))):
        fields = line.split()
        pts = dict(f.split("=") for f in fields[3:])
        for name, ref in REAL_REFERENCE.items():
            p = to_cam(tuple(float(x) for x in pts[name].split(",")))
            assert np.hypot(p[0] - ref[0], p[1] - ref[1]) <= 3.0, (line, name)
    # a joint the frame does not show: a reason, exit 1
    assert main(["detect", "--joint", "lap", str(REAL / "v_groove_spatter.png")]) == 1
    assert capsys.readouterr().out.split(" ", 1)[1].startswith("none: no step")


def test_part_joint_field(tmp_path):
    from torchseam.core.config import load_part

    assert load_part().joint == "fillet"
    text = (Path(__file__).parents[1] / "configs" / "parts" / "t_joint.yaml").read_text()
    good = tmp_path / "bevel.yaml"
    good.write_text(text + "joint: v_groove\n")
    assert load_part(good).joint == "v_groove"
    bad = tmp_path / "tee.yaml"
    bad.write_text(text + "joint: tee\n")
    with pytest.raises(ConfigError, match=r"tee.yaml: joint: .*'tee'"):
        load_part(bad)


def _saturated_butt(glare_below: float) -> np.ndarray:
    """A colour frame of a butt's stripe at row 240, broken at columns 310-330, bright enough to
    saturate R and G in its core (a wide stripe on arc light: its red excess is two ridges, its
    edges), over a glare-lit background; ``glare_below`` more green under the stripe dims its
    lower ridge."""
    h, w = 480, 640
    v = np.arange(h, dtype=float)[:, None]
    core = np.exp(-((v - 240.0) ** 2) / (2 * 3.5**2)) * np.ones((1, w))
    core[:, 310:331] = 0.0
    img = np.zeros((h, w, 3))
    img[..., 0] = 40.0
    img[..., 1] = 90.0 + 330.0 * core + glare_below * (v > 240.0)
    img[..., 2] = 140.0 + 420.0 * core
    return np.clip(img, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("glare_below", [0.0, 60.0])
def test_a_saturated_stripe_is_centred_on_its_saturated_run(glare_below):
    """A stripe saturated in R and G has no red excess in its core: the profile's centre line
    is the middle of the saturated run, not the stronger ridge (with the lower ridge dimmed
    by glare it sat on the upper one, ~4 px off); the butt's gap centre follows."""
    from torchseam.vision.profiles import saturated_centre

    img = _saturated_butt(glare_below)
    res = finder("butt")(img)
    assert res.ok, res.status
    lit = (res.centre[:, 0] < 309) | (res.centre[:, 0] > 331)   # (the mask spills into the gap)
    assert np.all(np.abs(res.centre[lit, 1] - 240.0) <= 0.6), res.centre[lit, 1].min()
    assert abs(res.aim[0] - 320.0) <= 1.0 and abs(res.aim[1] - 240.0) <= 0.6, res.aim
    # a saturated blob taller than the search (glare, not a stripe) moves no point
    blob = img.copy()
    blob[150:330, 100:200] = 255
    pts = np.array([[150.0, 234.0], [400.0, 234.0]])
    moved = saturated_centre(blob, pts, CFG.stripe.max_run_px)
    assert moved[0, 1] == 234.0 and abs(moved[1, 1] - 240.0) <= 0.5


def _glare_lap(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A colour frame of the lit-face lap of :func:`_lap_z` under the arc's glare, with its
    root and edge: a round glow (sigma 35 px) on the root that clips R over the joint; the
    stripe raises R and, overexposed into white, G and B too (0.35 and 0.28 of its R), as the
    simulator's white-cored stripe does."""
    pieces, root, edge = _lap_z(0.0)
    s = draw(pieces, seed=seed).astype(float)
    y, x = np.mgrid[0:480, 0:640].astype(float)
    glow = 0.9 * np.exp(-((x - root[0]) ** 2 + (y - root[1]) ** 2) / (2 * 35.0**2))
    img = np.stack([25 + 0.28 * s + 120 * glow, 30 + 0.35 * s + 150 * glow,
                    50 + s + 260 * glow], axis=2)
    return np.clip(img, 0, 255).astype(np.uint8), root, edge


@pytest.mark.parametrize("seed", [0, 1])
def test_a_lap_under_glare_that_clips_red_is_read_by_its_brightness(seed):
    """Glare clips R over the joint and the stripe is white there: its red excess dips at the
    stripe, and its centre line runs where R drops out of clipping beside it: the face's line
    off, the root slid along the far plate (before: 5.3 and 2.6 px off, as in the lap demo's
    seed 2, segment a). Glare clips R beyond the stripe's own width on more than
    white_core_fraction of the brightness's centre line within fit_px of the joint, and the
    two readings' joints lie within the stripe's width: the frame is read by its brightness,
    the root and the edge within 1 px. Without glare, and where only the stripe's own core is
    clipped (R and G, a wide stripe), the red excess reads it."""
    img, root, edge = _glare_lap(seed)
    res = finder("lap")(img)
    assert res.ok, res.status
    assert res.reason == ""   # the lit face, not LAP_DARK_FACE
    assert np.linalg.norm(res.points["root"] - root) <= 1.0, res.points
    assert np.linalg.norm(res.points["edge"] - edge) <= 1.0, res.points
    # no glare: nothing white, the red excess's profile as it is
    pieces, _, _ = _lap_z(0.0)
    s = draw(pieces, seed=seed).astype(float)
    clean = np.clip(np.stack([25 + 0.1 * s, 30 + 0.1 * s, 50 + s], axis=2), 0, 255).astype(
        np.uint8)
    assert not np.any((clean[..., 2] >= 250) & (clean[..., :2].max(axis=2) > 125))
    got, red = finder("lap")(clean), finder("lap")._profile(clean)
    assert got.ok and red.ok
    np.testing.assert_allclose(got.aim, red.aim)
    assert np.linalg.norm(got.points["root"] - root) <= 1.0
    # white in its own core only (R and G clipped over ~11 rows, none beside): no red excess
    # in the core, two ridges at its edges, so the red excess's ends, followed along the
    # centre line, ran past each other across the gap (columns 310-330 dark: read 333 and 307,
    # a gap of 26 px the wrong way round); it now reads no gap there, and the brightness,
    # read where the red excess gives none, puts the edges where the stripe's half brightness
    # is (h20)
    core = _saturated_butt(0.0)
    got, red = finder("butt")(core), finder("butt")._profile(core)
    assert not red.ok and "edges cross" in red.reason, red.status
    assert got.ok, got.status
    assert abs(got.points["left_edge"][0] - 309.5) <= 0.5, got.points
    assert abs(got.points["right_edge"][0] - 330.5) <= 0.5, got.points


def _fit_line_reference(p: np.ndarray, robust: bool = True
                        ) -> tuple[np.ndarray, np.ndarray, float]:
    """fit_line as numpy states it: the scatter matrix's eigenvector of the larger eigenvalue,
    refitted once on the points within 3 sigma (MAD) of the first fit."""
    c = p.mean(axis=0)
    _, vec = np.linalg.eigh(np.cov((p - c).T, bias=True))
    d = vec[:, 1]
    r = (p - c) @ np.array([-d[1], d[0]])
    if robust and len(p) >= 6:
        dev = np.abs(r - np.median(r))
        keep = dev <= max(3 * 1.4826 * np.median(dev), 1.0)
        if 2 <= keep.sum() < len(p):
            return _fit_line_reference(p[keep], robust=False)
    return c, (d if d[0] >= 0 else -d), float(np.sqrt(np.mean(r * r)))


@pytest.mark.parametrize("seed", range(6))
def test_compiled_line_fit_is_the_numpy_one(seed: int) -> None:
    """The compiled fit (closed-form direction, one median pass) gives numpy's line on noisy
    pieces with spatter dots, at any slope and on reversed (strided) views, and the true
    line within its noise."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(6, 200))
    ang = rng.uniform(-np.pi, np.pi)
    d_true = np.array([np.cos(ang), np.sin(ang)])
    t = np.sort(rng.uniform(-60, 60, n))
    p = rng.uniform(0, 400, 2) + t[:, None] * d_true + rng.normal(0, 0.4, (n, 1)) * np.array(
        [-d_true[1], d_true[0]])
    p[rng.choice(n, n // 10, replace=False)] += rng.normal(0, 15, (n // 10, 2))  # spatter
    for pts in (p, p[::-1]):
        for robust in (True, False):
            line = fit_line(pts, robust)
            c, d, rms = _fit_line_reference(np.ascontiguousarray(pts), robust)
            np.testing.assert_allclose(line.c, c, atol=1e-9)
            np.testing.assert_allclose(line.d, d, atol=1e-9)
            assert line.rms == pytest.approx(rms, abs=1e-9)
        assert line.d[0] >= 0
    clean = fit_line(p)
    assert abs(float(clean.d @ d_true)) > np.cos(np.radians(1.0))
