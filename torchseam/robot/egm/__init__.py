"""ABB Externally Guided Motion (EGM): the sensor end of the link to the robot controller.

- :mod:`~torchseam.robot.egm.messages`: the protobuf messages (``egm.proto``, shipped next to
  it) and the parsers of one datagram (:func:`parse_robot`, :func:`parse_sensor`).
- :mod:`~torchseam.robot.egm.policy`: the safety policy as pure functions (what may be
  commanded, what a hold commands, which datagram belongs to the session): no sockets, no
  threads, no clock read.
- :mod:`~torchseam.robot.egm.link`: :class:`EgmLink`, the UDP socket, the serving thread and
  the state the policy decides on.
- :mod:`~torchseam.robot.egm.stats`: the link's counters and latency summaries.
- :mod:`~torchseam.robot.egm.config`: ``configs/egm.yaml``.

The names other modules use are re-exported here (``from torchseam.robot.egm import EgmLink``).
The loopback session and the ``torchseam robot sim-controller`` command, which drive the
simulated controller against the link, are :mod:`torchseam.robot.egm_session` and
:mod:`torchseam.robot.egm_cli`: they import the simulated controller, which imports this
package. Nothing here imports torch.
"""

from torchseam.robot.egm.config import (
    MODES,
    EgmConfig,
    EgmLinkConfig,
    EgmNetwork,
    EgmSafety,
    SimControllerConfig,
    egm_config_from_dict,
    load_egm_config,
)
from torchseam.robot.egm.link import (
    SO_TIMESTAMPNS,
    TIMESPEC,
    EgmError,
    EgmLink,
    open_udp,
    rx_time_ns,
    set_realtime_priority,
)
from torchseam.robot.egm.messages import parse_robot, parse_sensor
from torchseam.robot.egm.policy import ACCEPTED, Gate, Verdict
from torchseam.robot.egm.stats import EgmStats, LateReply, copy_stats, latency_summary

__all__ = ["ACCEPTED", "MODES", "SO_TIMESTAMPNS", "TIMESPEC", "EgmConfig", "EgmError",
           "EgmLink", "EgmLinkConfig", "EgmNetwork", "EgmSafety", "EgmStats", "Gate",
           "LateReply", "SimControllerConfig", "Verdict", "copy_stats", "egm_config_from_dict",
           "latency_summary", "load_egm_config", "open_udp", "parse_robot", "parse_sensor",
           "rx_time_ns", "set_realtime_priority"]
