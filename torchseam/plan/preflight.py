"""Pre-flight check: the whole weld plan through the reachability gate before any motion.

:func:`preflight` plans the part (:func:`torchseam.plan.weld.plan_weld`: the configured plan,
or the searched one when the configured plan fails the gate), then runs every pose of every
segment (the approach included) through the gate the live loop will use, and returns a
:class:`PlanReport`: one row per segment with the poses, how many pass, the worst axis's margin
to its range or the reason a pose is refused, the clearance to the pipes, and the positioner
turn and torch angles chosen. ``torchseam plan --part FILE`` prints it (exit code 2 when the
robot cannot weld the part).

Example:
    >>> from torchseam.core.config import load_cell, load_part
    >>> from torchseam.plan.path import load_plan_config
    >>> from torchseam.robot.kinematics import load_irb1410
    >>> report = preflight(load_cell(), load_part(), config=load_plan_config(),
    ...                    robot=load_irb1410())
    >>> report.ok, [v.passed for v in report.verdicts]
    (True, [True, True, True, True, True, True])
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchseam.core.config import CellConfig, PartConfig
from torchseam.core.part import SegmentGeometry, make_joint
from torchseam.plan.path import PlanConfig
from torchseam.plan.weld import (
    SINGULARITY_AXIS,
    PlanEvaluator,
    SegmentVerdict,
    WeldPlan,
    configured_plan,
    plan_weld,
)
from torchseam.robot.kinematics import IRB1410

__all__ = ["PlanReport", "preflight"]


@dataclass(frozen=True)
class PlanReport:
    """A plan and the gate's verdict on every pose of it.

    Attributes:
        plan: the plan to weld (``plan.part`` carries its placement).
        verdicts: one :class:`~torchseam.plan.weld.SegmentVerdict` per segment, every pose.
        configured_plan: the plan as configured.
        configured: its verdicts when it failed the gate and the plan was searched (else None:
            ``plan`` is the configured plan).
        part_name: what to call the part in the table (its file).
        elapsed_s: time taken, search included.
    """

    plan: WeldPlan
    verdicts: tuple[SegmentVerdict, ...]
    configured_plan: WeldPlan
    configured: tuple[SegmentVerdict, ...] | None
    part_name: str = "part"
    elapsed_s: float = 0.0

    @property
    def ok(self) -> bool:
        """The robot can weld every pose of the plan."""
        return all(v.passed for v in self.verdicts)

    @property
    def refused(self) -> list[str]:
        """Names of the segments with a refused pose."""
        return [s.name for s, v in zip(self.plan.segments, self.verdicts, strict=True)
                if not v.passed]

    def table(self, configured: bool = False) -> str:
        """The per-segment table of the plan (or of the configured plan, when searched)."""
        plan = self.configured_plan if configured else self.plan
        verdicts = self.configured if configured else self.verdicts
        if verdicts is None:
            raise ValueError("the configured plan is the plan: table() shows it")
        rows = []
        geo = SegmentGeometry(plan.part)
        # where along the seam: degrees of branch angle round a ring, mm along an open seam
        along = ((lambda deg: deg % 360, "deg", "branch deg") if geo.nominal_joint.closed else
                 (lambda deg: float(geo.s_at(np.radians(deg))), "mm", "seam mm"))
        for seg, v in zip(plan.segments, verdicts, strict=True):
            a, b = along[0](np.degrees(seg.phi_start)), along[0](np.degrees(seg.phi_end))
            if v.passed:
                verdict = f"margin {v.margin_deg:.1f} deg ({_margin_name(v.margin_axis)})"
            else:
                where = (f"pose {v.first_refused} at "
                         f"{along[0](v.phi_deg[v.first_refused]):.0f} {along[1]}")
                counts = ", ".join(f"{k} {n}" for k, n in v.counts.items())
                verdict = f"REFUSED {v.poses - v.ok} ({counts}), first {where}: {v.reason}"
            rows.append([seg.name, f"{a:.0f}-{b:.0f}", str(v.poses), str(v.ok),
                         f"{v.clearance_mm:.1f}", f"{seg.rotation_deg + 0.0:.0f}",
                         "/".join(f"{x + 0.0:g}" for x in seg.angles), verdict])
        return _table(["segment", along[2], "poses", "reachable", "clearance mm",
                       "turn deg", "work/travel/roll deg", "worst joint margin or reason"], rows)

    def refused_line(self) -> str:
        """One line for a refused plan: which segments, the first refusal's reason."""
        seg, v = next((s, v) for s, v in zip(self.plan.segments, self.verdicts, strict=True)
                      if not v.passed)
        return (f"the robot cannot weld this plan: segment(s) {', '.join(self.refused)} "
                f"refused (segment {seg.name}: {v.reason}; see the reason column)")

    def text(self, verdict: bool = True) -> str:
        """The whole report: the plan's choices, its table (after the configured plan's, when
        that failed and the plan was searched) and the verdict (``verdict=False``: not the
        refusal line, which the caller reports as its error)."""
        p, c = self.plan, self.configured_plan
        pos = ", ".join(f"{x:.1f}" for x in p.part.placement.position_mm)
        quat = ", ".join(f"{x:.4f}" for x in p.part.placement.quaternion)
        out = [f"pre-flight of {self.part_name}: every pose of the six segments (approach "
               f"included) through the reachability gate ({self.elapsed_s:.1f} s)"]
        if self.configured is not None:
            start = (f"{c.segment_start_deg:g} deg" if make_joint(c.part).closed
                     else "the seam's start")
            out += ["", f"configured plan (placement as in the part file, segment a from "
                    f"{start}): refused on segment(s) "
                    + ", ".join(s.name for s, v in zip(c.segments, self.configured, strict=True)
                                if not v.passed), self.table(configured=True), "",
                    f"searched plan ({p.candidates} candidates screened in {p.search_s:.1f} s):"]
        elif self.ok:
            out += ["", "configured plan (it passes the gate: no search)"]
        else:  # refused and not searched (search=False)
            out += ["", "configured plan (not searched): refused on segment(s) "
                    + ", ".join(self.refused)]
        out += [f"  placement: {p.placement.describe()} (joint frame at ({pos}) mm, quaternion "
                f"({quat}))",
                (f"  segment a starts at {p.segment_start_deg:g} deg of branch angle"
                 + ("" if p.segment_start_deg == c.segment_start_deg
                    else f" (configured {c.segment_start_deg:g})"))
                if make_joint(p.part).closed else
                "  an open seam: six segments from its start to its end, the part not turned",
                self.table()]
        if self.ok:
            out.append(f"plan OK: {sum(v.poses for v in self.verdicts)} poses, worst joint margin "
                       f"{min(v.margin_deg for v in self.verdicts):.1f} deg, smallest clearance "
                       f"{min(v.clearance_mm for v in self.verdicts):.1f} mm")
        else:
            if verdict:
                out.append(self.refused_line())
            if p.searched and all(set(v.counts) <= {"clearance"} for v in self.verdicts):
                out.append("  only clearance refusals: the torch body (configs/robot.yaml torch: "
                           "nozzle and body radii, tip exclusion, clearance margin) does not "
                           "fit the joint there at any work/travel angle within "
                           "configs/plan.yaml's search limits")
        return "\n".join(out)

    def to_dict(self) -> dict:
        def rows(plan: WeldPlan, verdicts) -> list[dict]:
            return [{"segment": s.name, "poses": v.poses, "reachable": v.ok, "passed": v.passed,
                     "joint_margin_deg": v.margin_deg if np.isfinite(v.margin_deg) else None,
                     "margin_axis": v.margin_axis, "clearance_mm": v.clearance_mm,
                     "refused": v.counts, "first_refused": v.first_refused, "reason": v.reason}
                    for s, v in zip(plan.segments, verdicts, strict=True)]

        out = {"part": self.part_name, "ok": self.ok, "plan": self.plan.to_dict(),
               "segments": rows(self.plan, self.verdicts), "elapsed_s": round(self.elapsed_s, 3)}
        if self.configured is not None:
            out["configured"] = {"plan": self.configured_plan.to_dict(),
                                 "segments": rows(self.configured_plan, self.configured)}
        return out


def _margin_name(axis: int) -> str:
    return "singularity" if axis == SINGULARITY_AXIS else f"axis {axis}"


def _table(headers: list[str], rows: list[list[str]]) -> str:
    """Columns aligned, the last (text) column left-aligned, the others right-aligned."""
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(headers)]
    last = len(headers) - 1

    def line(cells: list[str]) -> str:
        return "  ".join(c.ljust(w) if i in (0, last) else c.rjust(w)
                         for i, (c, w) in enumerate(zip(cells, widths, strict=True))).rstrip()

    return "\n".join([line(headers), line(["-" * w for w in widths])] + [line(r) for r in rows])


def preflight(cell: CellConfig, part: PartConfig, *, config: PlanConfig, robot: IRB1410,
              search: bool = True, part_name: str | Path = "part") -> PlanReport:
    """Plan ``part`` and check every pose of the plan with the reachability gate.

    Args:
        cell: the cell (tool, weld speed, step, look-ahead).
        part: the part as its file describes it (its ``placement`` is the configured one).
        config: planning settings and search limits (``configs/plan.yaml``:
            :func:`~torchseam.plan.path.load_plan_config`).
        robot: the kinematic model whose config holds the gate's limits (``configs/robot.yaml``:
            :func:`~torchseam.robot.kinematics.load_irb1410`).
        search: search a plan when the configured one fails (False: check the configured plan
            only).
        part_name: what to call the part in the report.

    Returns:
        :class:`PlanReport`; ``report.ok`` says whether the robot can weld it, ``report.plan``
        is the plan to weld (``report.plan.part`` the part as placed).
    """
    t0 = time.perf_counter()
    ev = PlanEvaluator(cell, part, config, robot)
    conf = configured_plan(part, ev.config)
    conf_v = ev.check_plan(conf)
    if all(v.passed for v in conf_v) or not search:
        return PlanReport(conf, tuple(conf_v), conf, None, str(part_name),
                          time.perf_counter() - t0)
    plan = plan_weld(ev, configured=conf_v)
    verdicts = tuple(ev.check_plan(plan))
    return PlanReport(plan, verdicts, conf, tuple(conf_v), str(part_name),
                      time.perf_counter() - t0)
