"""chunkrt_ipc: the chunkrt message contract for Python (ctypes).

A mirror of ``ipc/src/messages.rs`` (types, constants, iceoryx2 type names) and of the quality
of service in ``ipc/src/services.rs``, so that a Python process opens the same iceoryx2 services
as the Rust processes with compatible settings. ``tests/ipc_layout.rs`` runs this file
(``python3 chunkrt_ipc.py --layouts``) and compares every size and field offset with Rust.

Only the service helpers at the bottom need the ``iceoryx2`` package (PyPI ``iceoryx2==0.10.0``);
the types and constants need nothing but the standard library.

Timestamps are CLOCK_MONOTONIC nanoseconds: use :func:`monotonic_ns` (``time.monotonic_ns`` is
CLOCK_MONOTONIC on Linux).
"""

import ctypes
import json
import sys
import time

# ---- contract -------------------------------------------------------------------------------

#: Largest number of joints a message can carry.
MAX_DOF = 16
#: Most actions a published chunk carries (``NS/chunks``).
MAX_CHUNK_HORIZON = 128
#: Version of the message contract; part of every type name.
CONTRACT_VERSION = 1

# ---- quality of service (ipc/src/services.rs) -----------------------------------------------

#: Subscriber buffer of the joint state / command / status services.
BUFFER_SIZE = 4
#: Subscriber buffer of a camera service.
CAMERA_BUFFER_SIZE = 2
#: Late joiners get the last sample.
HISTORY_SIZE = 1
#: Processes per service.
MAX_NODES = 16
#: Subscribers per service.
MAX_SUBSCRIBERS = 8
#: Publishers per service.
MAX_PUBLISHERS = 4
#: Samples a subscriber may hold at once.
SUBSCRIBER_MAX_BORROWED_SAMPLES = 2
#: Samples a publisher may loan at once.
PUBLISHER_MAX_LOANED_SAMPLES = 2
#: A full subscriber buffer drops its oldest sample.
ENABLE_SAFE_OVERFLOW = True

# ---- camera frames --------------------------------------------------------------------------

ENCODING_RGB8 = 1
ENCODING_BGR8 = 2
ENCODING_MONO8 = 3
ENCODING_NAMES = {ENCODING_RGB8: "rgb8", ENCODING_BGR8: "bgr8", ENCODING_MONO8: "mono8"}
BYTES_PER_PIXEL = {ENCODING_RGB8: 3, ENCODING_BGR8: 3, ENCODING_MONO8: 1}

# ---- joint state status flags ---------------------------------------------------------------

JOINT_STATUS_HOLDING = 1 << 0
JOINT_STATUS_COMMAND_EXPIRED = 1 << 1
JOINT_STATUS_COMMAND_TIMEOUT = 1 << 2
JOINT_STATUS_COMMAND_REJECTED = 1 << 3
JOINT_STATUS_LIMIT_CLAMPED = 1 << 4
JOINT_STATUS_SESSION_REPORTED = 1 << 5
JOINT_STATUS_COMMAND_FAR = 1 << 6
JOINT_STATUS_ROBOT_ERROR = 1 << 7
JOINT_STATUS_AT_REST = 1 << 8
JOINT_STATUS_NOT_FOLLOWING = 1 << 9  # the driver's own fallback leads the arm

# ---- command modes --------------------------------------------------------------------------

COMMAND_MODE_POSITION = 1
COMMAND_MODE_HOLD = 2

# ---- controller states ----------------------------------------------------------------------

CONTROLLER_STATE_STARTING = 0
CONTROLLER_STATE_HOLD = 1
CONTROLLER_STATE_RUNNING = 2
CONTROLLER_STATE_FAULT = 3
CONTROLLER_STATE_STOPPED = 4  # last status of a clean stop: the session is released
CONTROLLER_STATE_NOT_FOLLOWED = 5  # running, but the robot's driver leads the arm
CONTROLLER_STATE_NAMES = {
    0: "starting", 1: "hold", 2: "running", 3: "fault", 4: "stopped", 5: "not followed"
}

# ---- why the controller is in its state (ControllerStatus.state_reason, .rearm_reason) --------

STATE_REASON_NONE = 0
STATE_REASON_INPUTS_GOOD = 1
STATE_REASON_STALE_JOINT_STATE = 2
STATE_REASON_NO_CHUNK = 3
STATE_REASON_STALE_CAMERA = 4
STATE_REASON_CHUNK_EXPIRED = 5
STATE_REASON_NON_FINITE_ACTION = 6
STATE_REASON_BAD_CHUNK = 7
STATE_REASON_OVERRUNS = 8
STATE_REASON_HOLD_TIMEOUT = 9
STATE_REASON_BAD_JOINT_STATE = 10
STATE_REASON_GENERATOR_ERROR = 11
STATE_REASON_REARM = 12
STATE_REASON_INFERENCE_ERROR = 13
STATE_REASON_NOT_OBEYED = 14
STATE_REASON_ROBOT_NOT_FOLLOWING = 15

# ---- re-arm answers (ControllerStatus.rearm_result for request rearm_seq) ---------------------

REARM_NONE = 0
REARM_ACCEPTED = 1  # FAULT -> STARTING
REARM_REFUSED_NOT_IN_FAULT = 2
REARM_REFUSED_INPUTS = 3  # rearm_reason: the input still bad
REARM_MAX_AGE_NS = 1_000_000_000  # oldest request the controller acts on

# ---- rejection reasons (indices into ControllerStatus.rejected) -----------------------------

REJECT_REASON_COUNT = 9
REJECT_N_DOF = 0
REJECT_NON_FINITE = 1
REJECT_FRAME_GEOMETRY = 2
REJECT_UNKNOWN_CODE = 3
REJECT_OUT_OF_ORDER = 4
REJECT_FROM_FUTURE = 5
REJECT_STALE = 6
REJECT_OTHER = 7
REJECT_FOREIGN_PUBLISHER = 8
REJECT_REASON_NAMES = [
    "n_dof",
    "non_finite",
    "frame_geometry",
    "unknown_code",
    "out_of_order",
    "from_future",
    "stale",
    "other",
    "foreign_publisher",
]

# ---- iceoryx2 type names (must equal the Rust #[type_name]s) --------------------------------

TYPE_NAME_CAMERA_FRAME_HEADER = "chunkrt.CameraFrameHeader.v1"
TYPE_NAME_JOINT_STATE = "chunkrt.JointState.v2"
TYPE_NAME_JOINT_COMMAND = "chunkrt.JointCommand.v2"
TYPE_NAME_CONTROLLER_STATUS = "chunkrt.ControllerStatus.v4"
TYPE_NAME_REARM_REQUEST = "chunkrt.RearmRequest.v1"
TYPE_NAME_ACTION_CHUNK_MSG = "chunkrt.ActionChunk.v1"

_F64xDOF = ctypes.c_double * MAX_DOF


class CameraFrameHeader(ctypes.Structure):
    """User header of a camera frame; pixels are the sample's ``u8`` slice payload."""

    _fields_ = [
        ("seq", ctypes.c_uint64),
        ("capture_time_ns", ctypes.c_uint64),
        ("publish_time_ns", ctypes.c_uint64),
        ("camera_id", ctypes.c_uint32),
        ("encoding", ctypes.c_uint32),
        ("width", ctypes.c_uint32),
        ("height", ctypes.c_uint32),
        ("stride", ctypes.c_uint32),
        ("reserved", ctypes.c_uint32),
    ]

    @staticmethod
    def type_name() -> str:
        """The iceoryx2 type name."""
        return TYPE_NAME_CAMERA_FRAME_HEADER


class JointState(ctypes.Structure):
    """Measured joint state published by the robot driver."""

    _fields_ = [
        ("seq", ctypes.c_uint64),
        ("measurement_time_ns", ctypes.c_uint64),
        ("n_dof", ctypes.c_uint32),
        ("status_flags", ctypes.c_uint32),
        ("position", _F64xDOF),
        ("velocity", _F64xDOF),
        ("effort", _F64xDOF),
        # with JOINT_STATUS_SESSION_REPORTED: the command publisher the robot obeys (0: none)
        ("session_publisher_id", ctypes.c_uint64 * 2),
    ]

    def set_obeyed_publisher(self, publisher_id: int) -> None:
        """Reports the command publisher the robot obeys (0: none)."""
        self.status_flags |= JOINT_STATUS_SESSION_REPORTED
        self.session_publisher_id[0] = publisher_id & (2**64 - 1)
        self.session_publisher_id[1] = publisher_id >> 64

    @staticmethod
    def type_name() -> str:
        """The iceoryx2 type name."""
        return TYPE_NAME_JOINT_STATE


class JointCommand(ctypes.Structure):
    """Command published by the controller every control tick."""

    _fields_ = [
        ("seq", ctypes.c_uint64),
        ("publish_time_ns", ctypes.c_uint64),
        ("deadline_ns", ctypes.c_uint64),
        ("observation_seq", ctypes.c_uint64),
        ("chunk_id", ctypes.c_uint64),
        ("state_seq", ctypes.c_uint64),
        ("n_dof", ctypes.c_uint32),
        ("mode", ctypes.c_uint32),
        ("position", _F64xDOF),
        ("velocity", _F64xDOF),
        ("acceleration", _F64xDOF),
    ]

    @staticmethod
    def type_name() -> str:
        """The iceoryx2 type name."""
        return TYPE_NAME_JOINT_COMMAND


class ControllerStatus(ctypes.Structure):
    """Status published by the controller."""

    _fields_ = [
        ("seq", ctypes.c_uint64),
        ("publish_time_ns", ctypes.c_uint64),
        ("state", ctypes.c_uint32),
        ("n_dof", ctypes.c_uint32),
        ("ticks", ctypes.c_uint64),
        ("overruns", ctypes.c_uint64),
        ("chunks", ctypes.c_uint64),
        ("joint_states", ctypes.c_uint64),
        ("frames", ctypes.c_uint64),
        ("rejected", ctypes.c_uint64 * REJECT_REASON_COUNT),
        ("last_inference_latency_ns", ctypes.c_uint64),
        ("lateness_p50_ns", ctypes.c_uint64),
        ("lateness_p99_ns", ctypes.c_uint64),
        ("lateness_max_ns", ctypes.c_uint64),
        ("compute_p50_ns", ctypes.c_uint64),
        ("compute_p99_ns", ctypes.c_uint64),
        ("compute_max_ns", ctypes.c_uint64),
        ("joint_state_age_ns", ctypes.c_uint64),
        ("hold_entries", ctypes.c_uint64),
        ("stale_cameras", ctypes.c_uint64),
        # iceoryx2 unique id of the controller's joint-command publisher, [low, high] 64-bit
        # words (0: not known yet). Session binding (the Rust reference is
        # chunkrt_ipc::SessionGate): a robot obeys only commands whose sample publisher id is
        # the one announced by the status publisher it is bound to; nothing before the first
        # status, nothing while a second status publisher speaks, and a status with state
        # CONTROLLER_STATE_STOPPED ends the session (the next binds after a settling time).
        ("command_publisher_id", ctypes.c_uint64 * 2),
        ("rearm_seq", ctypes.c_uint64),  # seq of the last re-arm request answered (0: none)
        ("state_reason", ctypes.c_uint32),  # STATE_REASON_*: why in this state
        ("rearm_result", ctypes.c_uint32),  # REARM_* answer to rearm_seq
        ("rearm_reason", ctypes.c_uint32),  # with REARM_REFUSED_INPUTS: STATE_REASON_*
        ("foreign_statuses", ctypes.c_uint32),  # statuses from another publisher seen
    ]

    def command_publisher(self) -> int:
        """The announced command publisher id as one integer (0: none yet)."""
        return int(self.command_publisher_id[0]) | (int(self.command_publisher_id[1]) << 64)

    @staticmethod
    def type_name() -> str:
        """The iceoryx2 type name."""
        return TYPE_NAME_CONTROLLER_STATUS


class RearmRequest(ctypes.Structure):
    """Asks the controller to leave FAULT (``NS/rearm``); answered in its next status. Rejected
    and counted: seq 0, reserved != 0, older than REARM_MAX_AGE_NS, from the future."""

    _fields_ = [
        ("seq", ctypes.c_uint64),  # non-zero id, echoed in ControllerStatus.rearm_seq
        ("publish_time_ns", ctypes.c_uint64),
        ("reserved", ctypes.c_uint64),
    ]

    @staticmethod
    def type_name() -> str:
        """The iceoryx2 type name."""
        return TYPE_NAME_REARM_REQUEST


class ActionChunkMsg(ctypes.Structure):
    """Every chunk the controller's chunk source delivers (``NS/chunks``): what the policy
    predicted. Published by the inference thread; the control tick does nothing for it."""

    _fields_ = [
        ("seq", ctypes.c_uint64),
        ("publish_time_ns", ctypes.c_uint64),
        ("chunk_id", ctypes.c_uint64),  # JointCommand.chunk_id while it executes
        ("observation_seq", ctypes.c_uint64),  # JointState.seq behind the observation
        ("observation_time_ns", ctypes.c_uint64),
        ("ready_time_ns", ctypes.c_uint64),  # ready - observation = latency
        ("start_shift_ns", ctypes.c_uint64),  # action 0 is for observation + start shift
        ("period_ns", ctypes.c_uint64),
        ("delay_steps", ctypes.c_uint32),
        ("horizon", ctypes.c_uint32),  # rows of actions used
        ("n_dof", ctypes.c_uint32),  # columns of actions used
        ("reserved", ctypes.c_uint32),
        ("actions", _F64xDOF * MAX_CHUNK_HORIZON),
    ]

    @staticmethod
    def type_name() -> str:
        """The iceoryx2 type name."""
        return TYPE_NAME_ACTION_CHUNK_MSG


MESSAGE_TYPES = [CameraFrameHeader, JointState, JointCommand, ControllerStatus, RearmRequest,
                 ActionChunkMsg]


def layouts():
    """``{struct name: {"size": n, "align": a, "fields": [[name, offset, size], ...]}}``."""
    out = {}
    for t in MESSAGE_TYPES:
        out[t.__name__] = {
            "size": ctypes.sizeof(t),
            "align": ctypes.alignment(t),
            "type_name": t.type_name(),
            "fields": [
                [name, getattr(t, name).offset, getattr(t, name).size]
                for name, _ in t._fields_
            ],
        }
    return out


def constants():
    """Every integer constant of the contract, by its Rust name (the C header adds ``CHUNKRT_``)."""
    g = globals()
    prefixes = (
        "MAX_DOF",
        "MAX_CHUNK_HORIZON",
        "CONTRACT_VERSION",
        "BUFFER_SIZE",
        "CAMERA_BUFFER_SIZE",
        "HISTORY_SIZE",
        "MAX_NODES",
        "MAX_SUBSCRIBERS",
        "MAX_PUBLISHERS",
        "SUBSCRIBER_MAX_BORROWED_SAMPLES",
        "PUBLISHER_MAX_LOANED_SAMPLES",
        "ENABLE_SAFE_OVERFLOW",
        "ENCODING_",
        "JOINT_STATUS_",
        "COMMAND_MODE_",
        "CONTROLLER_STATE_",
        "REJECT_",
        "STATE_REASON_",
        "REARM_",
    )
    return {
        k: int(v)
        for k, v in g.items()
        if k.startswith(prefixes) and isinstance(v, (int, bool))
    }


def type_names():
    """iceoryx2 type names by struct name."""
    return {t.__name__: t.type_name() for t in MESSAGE_TYPES}


def monotonic_ns() -> int:
    """CLOCK_MONOTONIC nanoseconds, the time base of every chunkrt timestamp."""
    return time.clock_gettime_ns(time.CLOCK_MONOTONIC)


def is_finite(values) -> bool:
    """True if every value is a finite float."""
    return all(v == v and v not in (float("inf"), float("-inf")) for v in values)


def validate_joint_command(cmd: JointCommand, expected_dof=None):
    """Structural check like Rust's ``validate_joint_command``: ``None`` or a reason string."""
    n = cmd.n_dof
    if n == 0 or n > MAX_DOF:
        return "n_dof %d outside 1..=%d" % (n, MAX_DOF)
    if expected_dof is not None and n != expected_dof:
        return "n_dof %d but the robot has %d joints" % (n, expected_dof)
    if cmd.mode not in (COMMAND_MODE_POSITION, COMMAND_MODE_HOLD):
        return "unknown command mode code %d" % cmd.mode
    for field in ("position", "velocity", "acceleration"):
        if not is_finite(getattr(cmd, field)[:n]):
            return "%s is not finite" % field
    return None


# ---- service names and helpers (need the iceoryx2 package) ----------------------------------


def joint_state_name(ns: str) -> str:
    return ns + "/joint_state"


def joint_command_name(ns: str) -> str:
    return ns + "/joint_command"


def status_name(ns: str) -> str:
    return ns + "/status"


def chunks_name(ns: str) -> str:
    return ns + "/chunks"


def rearm_name(ns: str) -> str:
    return ns + "/rearm"


def camera_name(ns: str, camera: str) -> str:
    return ns + "/camera/" + camera


def node(name: str):
    """An iceoryx2 IPC node with signal handling left to the process (as in Rust)."""
    import iceoryx2 as iox2

    return (
        iox2.NodeBuilder.new()
        .name(iox2.NodeName.new(name))
        .signal_handling_mode(iox2.SignalHandlingMode.Disabled)
        .create(iox2.ServiceType.Ipc)
    )


def typed_service(node, name: str, payload_type):
    """Opens (or creates) a joint state / command / status service with chunkrt's QoS."""
    import iceoryx2 as iox2

    return (
        node.service_builder(iox2.ServiceName.new(name))
        .publish_subscribe(payload_type)
        .history_size(HISTORY_SIZE)
        .subscriber_max_buffer_size(BUFFER_SIZE)
        .subscriber_max_borrowed_samples(SUBSCRIBER_MAX_BORROWED_SAMPLES)
        .enable_safe_overflow(ENABLE_SAFE_OVERFLOW)
        .max_publishers(MAX_PUBLISHERS)
        .max_subscribers(MAX_SUBSCRIBERS)
        .max_nodes(MAX_NODES)
        .open_or_create()
    )


def camera_service(node, name: str):
    """Opens (or creates) a camera service (``u8`` slice + CameraFrameHeader) with chunkrt's QoS."""
    import iceoryx2 as iox2

    return (
        node.service_builder(iox2.ServiceName.new(name))
        .publish_subscribe(iox2.Slice[ctypes.c_uint8])
        .user_header(CameraFrameHeader)
        .history_size(HISTORY_SIZE)
        .subscriber_max_buffer_size(CAMERA_BUFFER_SIZE)
        .subscriber_max_borrowed_samples(SUBSCRIBER_MAX_BORROWED_SAMPLES)
        .enable_safe_overflow(ENABLE_SAFE_OVERFLOW)
        .max_publishers(MAX_PUBLISHERS)
        .max_subscribers(MAX_SUBSCRIBERS)
        .max_nodes(MAX_NODES)
        .open_or_create()
    )


def publisher(service):
    """A publisher with chunkrt's settings."""
    return (
        service.publisher_builder()
        .max_loaned_samples(PUBLISHER_MAX_LOANED_SAMPLES)
        .create()
    )


def subscriber(service, buffer_size: int = BUFFER_SIZE):
    """A subscriber keeping the last few samples."""
    return service.subscriber_builder().buffer_size(buffer_size).create()


if __name__ == "__main__":
    if "--layouts" in sys.argv[1:]:
        print(
            json.dumps(
                {
                    "layouts": layouts(),
                    "constants": constants(),
                    "type_names": type_names(),
                }
            )
        )
    else:
        print(__doc__)
