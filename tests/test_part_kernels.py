"""The joints' compiled ray casts (torchseam.core._kernels) against the numpy casts they
replaced: the same surface for every ray, the same misses, hits within 1e-9 mm (a plain
branch) and 1e-6 mm (a bevelled branch's march), on every main body."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest

from torchseam.core.config import load_part
from torchseam.core.part import (
    BEVEL_MARCH_POINTS,
    PLATE_HALF_MM,
    BevelledJoint,
    Joint,
    PipeJoint,
    PlateJoint,
    _entry_root,
    make_joint,
)

BEVEL = "configs/parts/t_joint_bevel.yaml"
#: the reference's halvings of a bracket (~3e-9 of it)
BISECT_STEPS = 30


def _roots(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both roots (smaller, larger) of A t^2 + B t + C = 0, ``inf`` where there are none."""
    disc = B * B - 4 * A * C
    ok = (disc >= 0) & (A > 1e-12)
    sq = np.sqrt(np.where(ok, disc, 0.0))
    den = np.where(ok, 2 * A, 1.0)
    return (np.where(ok, (-B - sq) / den, np.inf), np.where(ok, (-B + sq) / den, np.inf))


def _material(j: BevelledJoint, p: np.ndarray) -> np.ndarray:
    """(N,) > 0 where points (N, 3) of the wall's shell lie in the wall's material."""
    rho, phi, a = j._polar(p)
    base = j.root_height(phi)[0] + (rho - j.r_in) * j.tan_b
    return np.minimum(a - base, j.branch_top - a)


def numpy_hit_branch(j: BevelledJoint, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The reference: every ray marched over its whole stretch of the wall's shell at once,
    then the bracket before its first sample in the material bisected (numpy, (rays x
    samples))."""
    n = len(d)
    qa, da, A, B, qq = j._branch_quadric(o, d)
    t_out = _roots(A, B, qq - j.r**2)
    t_in = _roots(A, B, qq - j.r_in**2)
    start = np.maximum(t_out[0], 0.0)
    end = np.where(np.isfinite(t_in[0]) & (t_in[0] > start), t_in[0], t_out[1])
    ok = np.isfinite(t_out[0]) & (t_out[1] > 0.0) & (end > start)
    axial = (A <= 1e-12) & (qq <= j.r**2) & (qq >= j.r_in**2)
    start = np.where(axial, 0.0, start)
    end = np.where(axial, 2.0 * (abs(j.branch_top) + np.abs(qa)) + 1.0, end)
    ok |= axial
    t = np.full(n, np.inf)
    idx = np.flatnonzero(ok)
    if not len(idx):
        return t
    s0, s1, oo, dd = start[idx], end[idx], o[idx], d[idx]
    m = BEVEL_MARCH_POINTS
    ts = s0[:, None] + (s1 - s0)[:, None] * np.linspace(0.0, 1.0, m)
    pts = oo[:, None, :] + ts[..., None] * dd[:, None, :]
    inside = _material(j, pts.reshape(-1, 3)).reshape(len(idx), m) >= 0.0
    first = np.argmax(inside, axis=1)
    anyin = inside.any(axis=1)
    at_entry = anyin & (first == 0)
    t[idx[at_entry]] = s0[at_entry]
    k = np.flatnonzero(anyin & (first > 0))
    if len(k):
        lo, hi = ts[k, first[k] - 1], ts[k, first[k]]
        ok_, dk = oo[k], dd[k]
        for _ in range(BISECT_STEPS):
            mid = 0.5 * (lo + hi)
            m_in = _material(j, ok_ + mid[:, None] * dk) >= 0.0
            hi = np.where(m_in, mid, hi)
            lo = np.where(m_in, lo, mid)
        t[idx[k]] = hi
    return t


def _part(kind: str):
    """The bevel's groove on a main body of each kind (its deviations kept)."""
    part = load_part(BEVEL)
    if kind == "pipe":
        return part
    other = load_part({"plate": "configs/parts/pipe_on_plate.yaml",
                       "sphere": "configs/parts/pipe_on_sphere.yaml",
                       "offset": "configs/parts/offset_branch.yaml",
                       "y_joint": "configs/parts/y_joint_60.yaml"}[kind])
    return dataclasses.replace(other, bevel_deg=30.0, branch_wall_mm=8.0, root_gap_mm=2.0,
                               branch_ovality=0.01)


def _rays(j: Joint, rng: np.random.Generator, n: int
          ) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) origins ~150-400 mm from the root edge, (N, 3) unit directions aimed at points
    near it (most rays cross the groove, the wall or the bore, some the main body; a tenth
    come from below, through the main body into the wall), and a few along the branch axis
    (in the wall's shell and in the bore)."""
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    seam = j.seam(phi).point
    target = seam + rng.normal(0.0, 1.0, (n, 3)) * np.array([6.0, 6.0, 6.0])
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u[:, 2] = np.abs(u[:, 2]) + 0.2        # from above, mostly
    u[: n // 10, 2] *= -1.0                 # a tenth from below, through the main body
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    o = target + rng.uniform(150.0, 400.0, n)[:, None] * u
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # a few rays straight down the axis, in the wall's shell and in the bore
    k = min(8, n)
    rad = np.linspace(getattr(j, "r_in", j.r - 10.0) - 2.0, j.r - 0.5, k)
    ang = rng.uniform(0.0, 2.0 * np.pi, k)
    o[:k] = (j.o + rad[:, None] * (np.cos(ang)[:, None] * j._f1 + np.sin(ang)[:, None] * j._f2)
             + (j.branch_top - 50.0) * j.d)
    d[:k] = -j.d
    return o, d


def numpy_hit_main(j: Joint, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The reference: the main body's entry (a pipe, a plate's top face or a sphere)."""
    base = j.base if isinstance(j, BevelledJoint) else j
    if isinstance(base, PipeJoint):   # ((y + s)/a)^2 + (z/b)^2 = 1
        a, b = base.a, base.b
        y = o[:, 1] + base.s
        A = (d[:, 1] / a) ** 2 + (d[:, 2] / b) ** 2
        B = 2 * (y * d[:, 1] / a**2 + o[:, 2] * d[:, 2] / b**2)
        return _entry_root(A, B, (y / a) ** 2 + (o[:, 2] / b) ** 2 - 1.0)
    if isinstance(base, PlateJoint):   # the top face, from above
        down = (o[:, 2] > 0.0) & (d[:, 2] < -1e-12)
        t = np.where(down, -o[:, 2] / np.where(down, d[:, 2], -1.0), np.inf)
        p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
        inside = (np.abs(p[:, 0]) <= PLATE_HALF_MM) & (np.abs(p[:, 1]) <= PLATE_HALF_MM)
        return np.where(down & inside & (t > 0), t, np.inf)
    w = o - base.m
    return _entry_root(np.einsum("ij,ij->i", d, d), 2 * np.einsum("ij,ij->i", w, d),
                       np.einsum("ij,ij->i", w, w) - base.R**2)


def numpy_hit_cylinder(j: Joint, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The reference: a plain branch's entry, its outer cylinder between bottom and top."""
    qa, da, A, B, qq = j._branch_quadric(o, d)
    t = _entry_root(A, B, qq - j.r**2)
    h = qa + t * da
    return np.where((h > j.branch_bottom) & (h < j.branch_top), t, np.inf)


def numpy_raycast(j: Joint, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The reference ``raycast``: the main body's hit (cut to the branch's bore under a
    bevelled branch) and the branch's (marched in a bevelled one), both over all rays, the
    nearer kept."""
    o = np.broadcast_to(o, d.shape)
    t_main = numpy_hit_main(j, o, d)
    if isinstance(j, BevelledJoint):
        hit = np.isfinite(t_main)
        bore = j._polar(o + np.where(hit, t_main, 0.0)[:, None] * d)[0] < j.r_in
        t_main = np.where(hit & ~bore, t_main, np.inf)
        t_branch = numpy_hit_branch(j, o, d)
    else:
        t_branch = numpy_hit_cylinder(j, o, d)
    t = np.minimum(t_main, t_branch)
    return t, np.where(np.isinf(t), 0, np.where(t_main <= t_branch, 1, 2)).astype(np.int8)


def _same_cast(j, seed: int, n: int, atol: float):
    """``n`` random rays cast compiled and by the numpy reference: the same surface for every
    ray, hits within ``atol`` mm, misses at infinity. Returns the rays (o, d), the compiled
    distances and the reference's surfaces."""
    o, d = _rays(j, np.random.default_rng(seed), n)
    t_ref, s_ref = numpy_raycast(j, o, d)
    t, surface = j.raycast(o, d)
    np.testing.assert_array_equal(surface, s_ref)
    hit = s_ref > 0
    np.testing.assert_allclose(t[hit], t_ref[hit], rtol=0.0, atol=atol)
    assert np.isinf(t[~hit]).all()
    return o, d, t, s_ref


@pytest.mark.parametrize("kind", ["pipe", "offset", "y_joint", "plate", "sphere"])
def test_compiled_cast_is_the_numpy_march(kind: str) -> None:
    """The same surface for every ray (the same misses), hits within 1e-6 mm: on the bevel
    face (refined), the outer wall, the main body, past the root gap into the bore."""
    j = make_joint(_part(kind))
    assert isinstance(j, BevelledJoint)
    o, d, t, s_ref = _same_cast(j, 11, 6000, 1e-6)
    hit = s_ref > 0
    # every kind of answer is among them
    p = o[hit] + t[hit, None] * d[hit]
    face = (s_ref[hit] == 2) & (j._polar(p)[0] < j.r - 1e-3)
    assert face.sum() > 300 and (s_ref == 1).sum() > 300 and (s_ref == 0).sum() > 100
    assert (s_ref[hit] == 2).sum() - face.sum() > 300     # the outer wall
    if kind != "plate":   # (a plate is lit from above only: no ray reaches the wall past it)
        # rays whose march the main body's hit cuts short: the wall is there beyond it
        assert np.isfinite(numpy_hit_branch(j, o, d)[s_ref == 1]).sum() > 20


@pytest.mark.parametrize("kind", ["pipe", "offset", "y_joint", "plate", "sphere"])
def test_compiled_plain_cast_is_numpy_s(kind: str) -> None:
    """A plain branch (no bevel) on each main body, oval and round: the same surface for
    every ray, hits within 1e-9 mm."""
    for ovality in (0.0, 0.01):
        part = dataclasses.replace(_part(kind), bevel_deg=0.0, root_gap_mm=0.0,
                                   branch_wall_mm=0.0, branch_ovality=ovality)
        j = make_joint(part)
        assert not isinstance(j, BevelledJoint)
        s_ref = _same_cast(j, 3, 4000, 1e-9)[3]
        assert (s_ref == 1).sum() > 300 and (s_ref == 2).sum() > 300


@pytest.mark.parametrize("kind", ["pipe", "bevel"])
def test_one_origin_for_all_rays(kind: str) -> None:
    """One origin (3,) for all rays, and directions in any layout, are cast as given."""
    part = _part("pipe")
    j = make_joint(part if kind == "bevel" else dataclasses.replace(
        part, bevel_deg=0.0, root_gap_mm=0.0, branch_wall_mm=0.0))
    o, d = _rays(j, np.random.default_rng(2), 64)
    t, s = j.raycast(o[20], np.asfortranarray(d))
    t_ref, s_ref = j.raycast(np.repeat(o[20:21], 64, axis=0), np.ascontiguousarray(d))
    np.testing.assert_array_equal(t, t_ref)
    np.testing.assert_array_equal(s, s_ref)
    assert j.raycast(o[0], d[0])[0].shape == (1,)
    with pytest.raises(ValueError, match="origins"):
        j.raycast(o[:3], d[:5])


def test_building_a_joint_loads_no_kernels() -> None:
    """A joint loads its compiled casts on its first cast: commands that build joints and
    never cast (the planner, the gate) do not import numba for them."""
    code = """if True:
        import sys
        from torchseam.core.config import load_part
        from torchseam.core.part import make_joint
        j = make_joint(load_part(sys.argv[1]))
        assert "torchseam.core._kernels" not in sys.modules
        j.raycast(j.o + 500.0 * j.d, -j.d[None])
        assert "torchseam.core._kernels" in sys.modules
    """
    for path in (BEVEL, "configs/parts/t_joint.yaml"):
        r = subprocess.run([sys.executable, "-c", code, path], capture_output=True, text=True,
                           timeout=120)
        assert r.returncode == 0, r.stderr
