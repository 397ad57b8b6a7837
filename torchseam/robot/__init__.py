"""The ABB IRB 1410 and its controller link.

- :mod:`torchseam.robot.kinematics`: ``IRB1410`` (FK / Jacobian from the URDF via
  pytorch-kinematics, closed-form IK), controller <-> URDF joint conversion.
- :mod:`torchseam.robot.reach`: ``ReachGate``, the reachability gate for torch poses.
- :mod:`torchseam.robot.config`: ``configs/robot.yaml``.
- :mod:`torchseam.robot.egm`: the EGM link to the controller (wire messages, the safety policy
  as pure functions, the UDP link, its counters, ``configs/egm.yaml``);
  :mod:`torchseam.robot.egm_session`: a loopback session of the simulated controller against it.
- :mod:`torchseam.robot.cli`: ``torchseam robot fk | ik | check`` (and the EGM commands).

Nothing is imported here, so ``import torchseam.robot.egm`` does not pull in torch.
"""
