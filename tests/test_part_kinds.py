"""The part kinds (issue 26, item 2): a pipe on a plate, a nozzle on a sphere, a branch offset
from the main axis by design. Each simulated seam against its closed form, the ray caster on
each kind's surfaces, the labelled feature point on the rendered stripe, TIPM on clean frames,
the clearance solids and the pre-flight check, all with the T joint's configuration."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from torchseam.core.config import CONFIG_DIR, ConfigError, PartConfig, from_dict, load_part, to_dict
from torchseam.core.transforms import apply, invert
from torchseam.robot.reach import ReachGate, nominal_torch_poses
from torchseam.sim.joint import Joint, PipeJoint, PlateJoint, SphereJoint, make_joint
from torchseam.sim.scene import Scene, nominal_part, torch_frames
from torchseam.sim.sensor import LaserSensor, camera_pose
from torchseam.sim.sequence import SequenceSpec, simulate

PARTS = CONFIG_DIR / "parts"
KINDS = {"plate": "pipe_on_plate", "sphere": "pipe_on_sphere", "offset": "offset_branch"}
PHI = np.linspace(0.0, 2 * np.pi, 400, endpoint=False)


def _part(kind: str):
    return load_part(PARTS / f"{KINDS[kind]}.yaml")


def _on_branch(j: Joint, p: np.ndarray) -> np.ndarray:
    """(N,) residual of the (oval) branch cylinder's equation at ``p``."""
    q = p - j.o
    return (((q @ j.e1) / (j.r * j.k1)) ** 2 + ((q @ j.e2) / (j.r * j.k2)) ** 2) - 1.0


def _check_local_geometry(j: Joint, phi: np.ndarray) -> None:
    """Tangent in both tangent planes and equal to the numeric derivative; unit normals."""
    s = j.seam(phi)
    np.testing.assert_allclose(np.einsum("ij,ij->i", s.tangent, s.normal_main), 0, atol=1e-9)
    np.testing.assert_allclose(np.einsum("ij,ij->i", s.tangent, s.normal_branch), 0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(s.normal_main, axis=1), 1, atol=1e-12)
    h = 1e-6
    num = (j.seam(phi + h).point - j.seam(phi - h).point) / (2 * h)
    np.testing.assert_allclose(num / np.linalg.norm(num, axis=1, keepdims=True), s.tangent,
                               atol=1e-6)
    F = torch_frames(s)  # the torch bisects the corner on every kind
    np.testing.assert_allclose(np.einsum("ij,ij->i", F[:, :3, 2], s.normal_main),
                               np.einsum("ij,ij->i", F[:, :3, 2], s.normal_branch), atol=1e-9)


# --------------------------------------------------------------------------- configs

def test_shipped_kinds_load_and_pipe_files_load_unchanged():
    for kind, name in KINDS.items():
        assert load_part(PARTS / f"{name}.yaml").kind == kind
    t = load_part(PARTS / "t_joint.yaml")
    assert (t.kind, t.design_offset_mm, t.sphere_radius_mm, t.branch_ovality) == (
        "pipe", 0.0, 0.0, 0.0)
    assert isinstance(make_joint(t), PipeJoint)
    assert isinstance(make_joint(_part("plate")), PlateJoint)
    assert isinstance(make_joint(_part("sphere")), SphereJoint)
    off = make_joint(_part("offset"))
    assert isinstance(off, PipeJoint) and off.s == 18.0
    # written back (plan --out) and read again: the same part
    for kind in KINDS:
        assert from_dict(PartConfig, to_dict(_part(kind))) == _part(kind)


@pytest.mark.parametrize("change, message", [
    ({"kind": "plate"}, "main_od_mm: a part of kind plate has none"),
    ({"kind": "sphere", "main_od_mm": None, "main_ovality": None, "sphere_radius_mm": None},
     "sphere_radius_mm: missing"),
    ({"kind": "sphere", "main_od_mm": None, "main_ovality": None},  # given as 0
     r"sphere_radius_mm: the sphere's radius must be > 0, got 0\.0"),
    ({"main_od_mm": None}, "main_od_mm: missing"),
    ({"design_offset_mm": 5.0}, "design_offset_mm: a part of kind pipe has none"),
    ({"kind": "offset", "design_offset_mm": 24.0}, "branch radius plus its y offset"),
    ({"kind": "cone"}, "kind: expected one of pipe, offset, plate, sphere"),
])
def test_bad_kind_dimensions_are_refused(change, message):
    d = to_dict(load_part(PARTS / "t_joint.yaml"))
    for k, v in change.items():
        if v is None:
            d.pop(k)
        else:
            d[k] = v
    with pytest.raises(ConfigError, match=message):
        from_dict(PartConfig, d, "part.yaml")


# --------------------------------------------------------------------------- seams

def test_plate_seam_is_the_branch_circle_on_the_plate():
    part = _part("plate")
    nom = make_joint(nominal_part(part))
    r = part.branch_od_mm / 2
    closed = np.stack([r * np.cos(PHI), r * np.sin(PHI), np.zeros_like(PHI)], axis=1)
    np.testing.assert_allclose(nom.seam(PHI).point, closed, atol=1e-9)
    np.testing.assert_allclose(nom.seam(PHI).normal_main, np.tile([0, 0, 1.0], (len(PHI), 1)))
    # the true part: its oval, offset branch's section by z = 0; also a leaning branch
    for p in (part, dataclasses.replace(part, intersection_angle_deg=70.0)):
        j = make_joint(p)
        pts = j.seam(PHI).point
        np.testing.assert_allclose(pts[:, 2], 0, atol=1e-9)
        np.testing.assert_allclose(_on_branch(j, pts), 0, atol=1e-12)
        _check_local_geometry(j, PHI[::10])


def test_sphere_seam_lies_on_the_sphere_and_the_branch():
    part = _part("sphere")
    R, r = part.sphere_radius_mm, part.branch_od_mm / 2
    nom = make_joint(nominal_part(part))
    closed = np.stack([r * np.cos(PHI), r * np.sin(PHI),
                       np.full_like(PHI, np.sqrt(R**2 - r**2))], axis=1)
    np.testing.assert_allclose(nom.seam(PHI).point, closed, atol=1e-9)
    # the true part, a leaning nozzle and a hillside nozzle (its axis 60 mm off the centre)
    for p in (part, dataclasses.replace(part, intersection_angle_deg=75.0),
              dataclasses.replace(part, design_offset_mm=60.0)):
        j = make_joint(p)
        pts = j.seam(PHI).point
        np.testing.assert_allclose(np.linalg.norm(pts - j.m, axis=1), R, atol=1e-9)
        np.testing.assert_allclose(_on_branch(j, pts), 0, atol=1e-12)
        assert ((pts - j.o) @ j.d > 0).all()   # where the nozzle leaves the head
        _check_local_geometry(j, PHI[::10])
    hill = make_joint(dataclasses.replace(part, design_offset_mm=60.0)).seam(PHI).point
    assert np.ptp(hill[:, 2]) > 40.0   # a hillside nozzle's seam is not planar


def test_offset_branch_seam_lies_on_both_cylinders():
    part = _part("offset")
    R, r, s = part.main_od_mm / 2, part.branch_od_mm / 2, part.design_offset_mm
    assert r + s < R - 5.0   # set on, with a margin
    nom = make_joint(nominal_part(part))
    y = r * np.sin(PHI) + s   # from the main axis
    closed = np.stack([r * np.cos(PHI), r * np.sin(PHI), np.sqrt(R**2 - y**2)], axis=1)
    np.testing.assert_allclose(nom.seam(PHI).point, closed, atol=1e-9)
    for p in (part, dataclasses.replace(part, intersection_angle_deg=65.0)):
        j = make_joint(p)
        pts = j.seam(PHI).point
        np.testing.assert_allclose(((pts[:, 1] + j.s) / j.a) ** 2 + (pts[:, 2] / j.b) ** 2, 1,
                                   atol=1e-12)
        np.testing.assert_allclose(_on_branch(j, pts), 0, atol=1e-12)
        _check_local_geometry(j, PHI[::10])


@pytest.mark.parametrize("kind", list(KINDS))
def test_raycast_hits_lie_on_the_surfaces_first(kind):
    j = make_joint(dataclasses.replace(_part(kind), intersection_angle_deg=75.0))
    main = j.main_solid()
    rng = np.random.default_rng(1)
    origin = main["origin"] + np.array([20.0, 150.0, 450.0])
    target = main["origin"] + rng.uniform([-150, -150, 0], [150, 150, 300], (600, 3))
    d = (target - origin) / np.linalg.norm(target - origin, axis=1, keepdims=True)
    t, surf = j.raycast(origin, d)
    assert (surf == 1).sum() > 50 and (surf == 2).sum() > 50
    P = origin + t[:, None] * d
    Pm, Pb = P[surf == 1], P[surf == 2]
    np.testing.assert_allclose(_on_main(j, Pm), 0, atol=1e-9)
    np.testing.assert_allclose(_on_branch(j, Pb), 0, atol=1e-9)
    # the first hit of the union: main-body hits outside the branch (or below its solid),
    # branch hits outside the main body
    assert ((_on_branch(j, Pm) >= -1e-9) | ((Pm - j.o) @ j.d <= j.branch_bottom)).all()
    assert (_on_main(j, Pb) >= -1e-9).all()


def _on_main(j: Joint, p: np.ndarray) -> np.ndarray:
    """(N,) residual of the main body's surface equation at ``p`` (> 0 outside)."""
    if isinstance(j, PlateJoint):
        return p[:, 2]
    if isinstance(j, SphereJoint):
        return np.linalg.norm(p - j.m, axis=1) - j.R
    return ((p[:, 1] + j.s) / j.a) ** 2 + (p[:, 2] / j.b) ** 2 - 1.0


# --------------------------------------------------------------------------- the sensor

@pytest.fixture(scope="module")
def clean_frames(cell, noise):
    """Per kind, four clean frames spread round the seam (rendered, with truth and view)."""
    out = {}
    sensor = LaserSensor(cell)
    for kind in KINDS:
        part = _part(kind)
        scene = Scene(part)
        frames = []
        for k, s0 in enumerate(np.linspace(0, scene.seam_length_mm, 4, endpoint=False) + 30.0):
            img, truth = next(iter(simulate(cell, part, noise, SequenceSpec(
                n_frames=1, level=0.0, seed=k, start_mm=float(s0)))))
            T_T_C = invert(scene.part_pose(truth.t_s)) @ camera_pose(cell, truth.T_B_W)
            view = sensor.view(scene.true_joint, T_T_C, float(scene.phi_at(s0)))
            frames.append((img, truth, view))
        out[kind] = (scene, frames)
    return out


@pytest.mark.parametrize("kind", list(KINDS))
def test_label_lies_on_the_rendered_stripe(kind, clean_frames):
    scene, frames = clean_frames[kind]
    j = scene.true_joint
    for img, truth, view in frames:
        assert truth.visible
        np.testing.assert_allclose(view.seam_uv, truth.uv, atol=1e-9)
        # the seam point is on both surfaces and is the stripe's corner sample
        s_T = apply(invert(scene.part_pose(truth.t_s)), truth.seam_B)
        assert abs(_on_branch(j, s_T[None])[0]) < 1e-9
        assert abs(_on_main(j, s_T[None])[0]) < 1e-9
        k = int(np.argmin(np.linalg.norm(view.uv - truth.uv, axis=1)))
        assert view.surface[k] == 3 and np.linalg.norm(view.uv[k] - truth.uv) < 1e-9
        assert {1, 2} <= set(view.surface.tolist())
        # in the image: the label is on the stripe's bright ridge (the corner's pixels are a
        # little dimmer than the arms': only one side of each arm reaches them)
        red = img[..., 2].astype(np.float32)
        at = float(cv2.getRectSubPix(red, (1, 1), (float(truth.uv[0]), float(truth.uv[1])))[0, 0])
        u, v = np.round(truth.uv).astype(int)
        assert at > 0.7 * red[v - 2:v + 3, u - 2:u + 3].max() and at > 100


@pytest.mark.parametrize("kind", list(KINDS))
def test_tipm_finds_the_corner_on_clean_frames(kind, clean_frames, tipm):
    for img, truth, _ in clean_frames[kind][1]:
        res = tipm(img)
        assert res.ok, res.reason
        assert np.linalg.norm(res.uv - truth.uv) < 0.5


# --------------------------------------------------------------------------- robot side

def test_clearance_solids_of_plate_and_sphere(cell, parts):
    for kind, name in (("plate", "plate"), ("sphere", "sphere")):
        part = _part(kind)
        gate = ReachGate(parts.robot, cell=cell, part=part)
        T = nominal_torch_poses(part, 12).numpy()
        c = gate._clearance(T)  # noqa: SLF001 - the solids, without the IK
        assert (c > 2.0).all()
        # the torch pushed 30 mm into the main body along its axis hits it (not the branch)
        T2 = T.copy()
        T2[:, :3, 3] += 30.0 * T[:, :3, 2]
        assert (gate._clearance(T2)[:, 0] < 0).all()  # noqa: SLF001
        assert gate._pipes.names[0] == name  # noqa: SLF001


@pytest.mark.parametrize("kind", list(KINDS))
def test_preflight_plans_every_kind(kind, cell, parts):
    from torchseam.plan.preflight import preflight

    report = preflight(cell, _part(kind), config=parts.plan, robot=parts.robot,
                       part_name=KINDS[kind])
    assert report.ok, report.text()
    assert min(v.clearance_mm for v in report.verdicts) > 2.0


def test_seam_point_is_the_seams_point_to_the_bit():
    """``Joint.seam_point`` (the sensor's root searches along the seam) gives the points of
    ``Joint.seam`` to the bit on every shipped part, ring and open seam, bevel, butt and lap."""
    phi = np.r_[np.linspace(-0.3, 2 * np.pi + 0.3, 397), [0.0, np.pi / 2, np.pi]]
    for path in sorted(PARTS.glob("*.yaml")):
        j = make_joint(load_part(path))
        np.testing.assert_array_equal(j.seam_point(phi), j.seam(phi).point, err_msg=path.name)
        np.testing.assert_array_equal(j.seam_point(phi[:1]), j.seam(phi[:1]).point)
