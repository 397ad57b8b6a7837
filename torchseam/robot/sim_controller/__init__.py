"""A simulated IRC5 controller that speaks EGM on loopback, with the IRB 1410 model.

Every cycle (``sim_controller.rate_hz``, 250 Hz = 4 ms by default) it sends an ``EgmRobot`` to
the sensor: feedback joints and TCP pose (forward kinematics of
:class:`~torchseam.robot.kinematics.IRB1410` and the cell's tool), the planned joints and pose,
motor / MCI / RAPID state, the wall clock, and its utilisation. Between cycles it waits for the
sensor's replies and moves the robot:

- ``mode: pose`` (``EgmSensor``): the planned TCP pose moves towards the latest received target
  at ``tcp_speed_mm_s`` / ``tcp_rot_speed_deg_s``.
- ``mode: pathcorr`` (``EgmSensorPathCorr``): the robot runs a programmed path (TCP poses,
  default a straight line from the home pose, ``path_direction`` / ``path_length_mm``) at
  ``path_speed_mm_s``; the received offset, given in the nominal TCP frame, is applied at most
  ``correction_speed_mm_s`` fast.

Fault injection for tests (:meth:`SimController.inject`, applied to the next N cycles; the
kinds are :class:`Fault`) and random packet loss in bursts (:meth:`SimController.set_loss`,
:class:`BurstLoss`) work in lockstep and on the socket alike.

One concern a module, each testable without the others:

- :mod:`.arm`: the robot: joints following the planned pose within the speed limits, the
  programmed path; kinematics from :mod:`torchseam.robot.kinematics` (numpy closed form).
- :mod:`.faults`: what happens to a datagram on its way out (:class:`Fault`,
  :class:`BurstLoss`, the fault plan); no sockets, no clocks.
- :mod:`.messages`: building and stamping ``EgmRobot``, reading the sensor's command.
- :mod:`.stats`: the counters (:class:`SimStats`).
- :mod:`.controller`: :class:`SimController`, the socket, the cycle loop and its thread, the
  lockstep cycle; it wires the others together.

The package keeps the name of the module it replaces: it is the name of the ``sim_controller``
section of ``configs/egm.yaml`` it runs on and of ``torchseam robot sim-controller``, and every
caller's ``from torchseam.robot.sim_controller import ...`` stays as it was.
"""

from torchseam.robot.sim_controller.arm import straight_path
from torchseam.robot.sim_controller.controller import SimController
from torchseam.robot.sim_controller.faults import BurstLoss, Fault
from torchseam.robot.sim_controller.stats import SimStats

__all__ = ["BurstLoss", "Fault", "SimController", "SimStats", "straight_path"]
