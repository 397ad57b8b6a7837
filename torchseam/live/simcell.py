"""The simulated cell for the closed loop: controller and sensor link stepped in sim time.

The simulated IRC5 controller and the EGM link exchange real wire bytes (``EgmRobot`` out,
``EgmSensor`` back) every 4 ms cycle, but in lockstep with the simulation clock instead of
through sockets and the wall clock: the demo then runs faster than real time and gives the
same result on a loaded 2-core machine as on an idle one. The live loop talks to the same
:class:`~torchseam.robot.egm.EgmLink` it would use with a real controller.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import torch

from torchseam.core.config import CellConfig
from torchseam.core.transforms import invert
from torchseam.robot.egm import EgmConfig, EgmLink
from torchseam.robot.kinematics import IRB1410
from torchseam.robot.sim_controller import SimController


class SimClock:
    """Simulation time in seconds; the link's clock in the demo."""

    def __init__(self, t0: float = 0.0) -> None:
        self.t = t0

    def __call__(self) -> float:
        return self.t


@dataclass
class CellFaults:
    """Link faults for this cycle window (counts of cycles left)."""

    drop_cycles: int = 0       # controller datagrams lost on the way
    silent_cycles: int = 0     # the controller sends nothing
    dropped: int = 0
    silent: int = 0
    log: list[str] = field(default_factory=list)


class LockstepCell:
    """A :class:`SimController` in pose mode and an :class:`EgmLink`, stepped together.

    Args:
        cell: the cell (tool = TCP in the flange).
        egm: EGM configuration (mode is forced to ``pose``: the demo guides full torch poses).
        link: the sensor-side link (``bind=False``, clock = ``clock``).
        clock: the simulation clock, advanced by :meth:`advance`.
        T_B_W0: (4, 4) torch pose to start from (the controller's joints by IK).
        robot: the controller's kinematic model (the reachability gate's, in the demo).
    """

    def __init__(self, cell: CellConfig, egm: EgmConfig, link: EgmLink, clock: SimClock,
                 T_B_W0: np.ndarray, robot: IRB1410) -> None:
        egm = dataclasses.replace(egm, mode="pose")
        self.ctrl = SimController(egm, mode="pose", robot=robot, tool=cell.tool.matrix(),
                                  bind_address=("127.0.0.1", 0))
        self.link = link
        self.clock = clock
        self.period = self.ctrl.period
        self.tool_inv = invert(cell.tool.matrix())
        q, ok = self.ctrl.robot.ik(torch.tensor((T_B_W0 @ self.tool_inv)[None]),
                                   torch.tensor(self.ctrl.q[None]))
        if not bool(ok[0]):
            raise RuntimeError("the segment's start pose is out of the robot's reach")
        self.ctrl.rest_at(q[0].numpy().astype(float))
        self.faults = CellFaults()
        self.sender = ("127.0.0.1", egm.network.controller_port or 6511)

    def close(self) -> None:
        """Close the controller's socket (it is never used in lockstep)."""
        self.ctrl.stop()

    def tcp_pose(self) -> np.ndarray:
        """The torch's actual pose now (forward kinematics of the joints), (4, 4) mm."""
        return self.ctrl.tcp_pose()

    def flange_pose(self) -> np.ndarray:
        return self.tcp_pose() @ self.tool_inv

    def advance(self, dt: float) -> None:
        """Run the EGM cycles that fit in ``dt`` seconds of simulation time."""
        for _ in range(max(1, int(round(dt / self.period)))):
            self._cycle()

    def _cycle(self) -> None:
        f = self.faults
        self.clock.t += self.period  # the link answers at the end of the cycle
        if f.silent_cycles > 0:
            f.silent_cycles -= 1
            f.silent += 1
            self.ctrl.step_lockstep(None)
            return
        self.ctrl.step_lockstep(self._exchange)

    def _exchange(self, data: bytes) -> bytes | None:
        """The wire between controller and link: loses the datagram during a drop fault."""
        f = self.faults
        if f.drop_cycles > 0:
            f.drop_cycles -= 1
            f.dropped += 1
            return None
        return self.link.handle_datagram(data, self.sender)
