/*
 * chunkrt_ipc.h: the chunkrt message contract for C and C++ processes.
 *
 * A mirror of ipc/src/messages.rs and of the quality-of-service numbers in
 * ipc/src/services.rs. The test suite (tests/ipc_layout.rs) compiles this header and checks
 * every size and field offset against the Rust definitions, so a drift fails the build.
 *
 * Rules of the contract:
 *  - fixed-size, naturally aligned structs, no pointers; codes are uint32_t constants;
 *  - every type name carries the contract version (".v1"): a changed layout gets a new name;
 *  - timestamps are CLOCK_MONOTONIC nanoseconds (uint64_t);
 *  - joint arrays hold CHUNKRT_MAX_DOF entries, only the first n_dof are meaningful.
 *
 * Services (see chunkrt_ipc::services::Namespace), publish-subscribe, for namespace NS:
 *   NS/joint_state    payload JointState,       user header none
 *   NS/joint_command  payload JointCommand,     user header none
 *   NS/status         payload ControllerStatus, user header none
 *   NS/rearm          payload RearmRequest,     user header none
 *   NS/chunks         payload ActionChunkMsg,   user header none
 *   NS/camera/NAME    payload uint8_t[] (slice, "u8"), user header CameraFrameHeader
 */
#ifndef CHUNKRT_IPC_H
#define CHUNKRT_IPC_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* ---- contract ------------------------------------------------------------------------- */

/** Largest number of joints a message can carry. */
#define CHUNKRT_MAX_DOF 16
/** Version of the message contract; part of every type name. */
#define CHUNKRT_CONTRACT_VERSION 1u

/* iceoryx2 type names (must equal the Rust #[type_name]s). */
#define CHUNKRT_TYPE_NAME_CAMERA_FRAME_HEADER "chunkrt.CameraFrameHeader.v1"
#define CHUNKRT_TYPE_NAME_JOINT_STATE "chunkrt.JointState.v2"
#define CHUNKRT_TYPE_NAME_JOINT_COMMAND "chunkrt.JointCommand.v2"
#define CHUNKRT_TYPE_NAME_CONTROLLER_STATUS "chunkrt.ControllerStatus.v4"
#define CHUNKRT_TYPE_NAME_REARM_REQUEST "chunkrt.RearmRequest.v1"
#define CHUNKRT_TYPE_NAME_ACTION_CHUNK_MSG "chunkrt.ActionChunk.v1"
/** Element type name of the camera pixel slice. */
#define CHUNKRT_TYPE_NAME_PIXEL "u8"

/* ---- quality of service (ipc/src/services.rs) ------------------------------------------ */

/** Subscriber buffer of the joint state / command / status services. */
#define CHUNKRT_BUFFER_SIZE 4
/** Subscriber buffer of a camera service. */
#define CHUNKRT_CAMERA_BUFFER_SIZE 2
/** Late joiners get the last sample. */
#define CHUNKRT_HISTORY_SIZE 1
/** Processes per service. */
#define CHUNKRT_MAX_NODES 16
/** Subscribers per service. */
#define CHUNKRT_MAX_SUBSCRIBERS 8
/** Publishers per service. */
#define CHUNKRT_MAX_PUBLISHERS 4
/** Samples a subscriber may hold at once. */
#define CHUNKRT_SUBSCRIBER_MAX_BORROWED_SAMPLES 2
/** Samples a publisher may loan at once. */
#define CHUNKRT_PUBLISHER_MAX_LOANED_SAMPLES 2
/** Safe overflow: a full subscriber buffer drops its oldest sample (1 = enabled). */
#define CHUNKRT_ENABLE_SAFE_OVERFLOW 1

/* ---- camera frames --------------------------------------------------------------------- */

/** 8-bit RGB, 3 bytes per pixel. */
#define CHUNKRT_ENCODING_RGB8 1u
/** 8-bit BGR, 3 bytes per pixel. */
#define CHUNKRT_ENCODING_BGR8 2u
/** 8-bit grey, 1 byte per pixel. */
#define CHUNKRT_ENCODING_MONO8 3u

/** User header of a camera frame; the pixels are the sample's uint8_t payload
 *  (stride * height bytes, rows top to bottom). */
typedef struct CameraFrameHeader {
    uint64_t seq;             /**< frame counter of this camera, +1 per frame */
    uint64_t capture_time_ns; /**< when the image was exposed (monotonic ns) */
    uint64_t publish_time_ns; /**< when the sample was handed to iceoryx2 (monotonic ns) */
    uint32_t camera_id;       /**< index of the camera in the robot's configuration */
    uint32_t encoding;        /**< CHUNKRT_ENCODING_* */
    uint32_t width;           /**< pixels per row */
    uint32_t height;          /**< rows */
    uint32_t stride;          /**< bytes per row: width * bpp ..= 2 * width * bpp + 256 */
    uint32_t reserved;        /**< zero */
} CameraFrameHeader;

/* ---- joint state (robot -> controller) ------------------------------------------------- */

/** The robot's watchdog holds position (no fresh, in-deadline command). */
#define CHUNKRT_JOINT_STATUS_HOLDING (1u << 0)
/** The last command arrived after its deadline and was ignored. */
#define CHUNKRT_JOINT_STATUS_COMMAND_EXPIRED (1u << 1)
/** No command arrived for longer than the robot's command timeout. */
#define CHUNKRT_JOINT_STATUS_COMMAND_TIMEOUT (1u << 2)
/** The last command failed validation. */
#define CHUNKRT_JOINT_STATUS_COMMAND_REJECTED (1u << 3)
/** A commanded value was outside the robot's limits and was clamped. */
#define CHUNKRT_JOINT_STATUS_LIMIT_CLAMPED (1u << 4)
/** session_publisher_id is set: the command publisher the robot obeys (0: none). A robot that
 *  sets it lets the controller hold and hand over bumplessly when it is not the one obeyed. */
#define CHUNKRT_JOINT_STATUS_SESSION_REPORTED (1u << 5)
/** The last command was refused: it started too far from the measured position. */
#define CHUNKRT_JOINT_STATUS_COMMAND_FAR (1u << 6)
/** The robot itself reports an error or a reflex and follows no command until it clears. */
#define CHUNKRT_JOINT_STATUS_ROBOT_ERROR (1u << 7)
/** The driver holds the arm still at its own commanded position (its commanded velocity and
 *  acceleration are zero): a controller that starts from this state starts at rest, whatever the
 *  measured velocity's noise says. */
#define CHUNKRT_JOINT_STATUS_AT_REST (1u << 8)
/* the driver's own fallback leads the arm, not the controller's commands */
#define CHUNKRT_JOINT_STATUS_NOT_FOLLOWING (1u << 9)

/** Measured joint state published by the robot driver. */
typedef struct JointState {
    uint64_t seq;                      /**< +1 per message */
    uint64_t measurement_time_ns;      /**< when the joints were measured (monotonic ns) */
    uint32_t n_dof;                    /**< valid joints, 1 ..= CHUNKRT_MAX_DOF */
    uint32_t status_flags;             /**< CHUNKRT_JOINT_STATUS_* bits */
    double position[CHUNKRT_MAX_DOF];  /**< rad or m */
    double velocity[CHUNKRT_MAX_DOF];  /**< per second */
    double effort[CHUNKRT_MAX_DOF];    /**< N*m or N */
    uint64_t session_publisher_id[2];  /**< with SESSION_REPORTED: the obeyed command publisher, low word first */
} JointState;

/* ---- joint command (controller -> robot) ----------------------------------------------- */

/** Track position, with velocity and acceleration as feed-forward. */
#define CHUNKRT_COMMAND_MODE_POSITION 1u
/** Hold the commanded position. */
#define CHUNKRT_COMMAND_MODE_HOLD 2u

/** Command published by the controller every control tick. */
typedef struct JointCommand {
    uint64_t seq;                         /**< +1 per tick */
    uint64_t publish_time_ns;             /**< monotonic ns */
    uint64_t deadline_ns;                 /**< must not be applied after this (monotonic ns) */
    uint64_t observation_seq;             /**< joint state seq behind the chunk (0: none) */
    uint64_t chunk_id;                    /**< action chunk id (0: none) */
    uint64_t state_seq;                   /**< newest joint state seq the tick had (0: none) */
    uint32_t n_dof;                       /**< valid joints */
    uint32_t mode;                        /**< CHUNKRT_COMMAND_MODE_* */
    double position[CHUNKRT_MAX_DOF];     /**< target positions */
    double velocity[CHUNKRT_MAX_DOF];     /**< target velocities */
    double acceleration[CHUNKRT_MAX_DOF]; /**< target accelerations */
} JointCommand;

/* ---- controller status (controller -> anyone) ------------------------------------------ */

#define CHUNKRT_CONTROLLER_STATE_STARTING 0u
#define CHUNKRT_CONTROLLER_STATE_HOLD 1u
#define CHUNKRT_CONTROLLER_STATE_RUNNING 2u
#define CHUNKRT_CONTROLLER_STATE_FAULT 3u
#define CHUNKRT_CONTROLLER_STATE_STOPPED 4u /* last status of a clean stop: session released */
#define CHUNKRT_CONTROLLER_STATE_NOT_FOLLOWED 5u /* running; the robot's driver leads the arm */

/* Rejection reasons: indices into ControllerStatus.rejected. */
#define CHUNKRT_REJECT_REASON_COUNT 9
#define CHUNKRT_REJECT_N_DOF 0u
#define CHUNKRT_REJECT_NON_FINITE 1u
#define CHUNKRT_REJECT_FRAME_GEOMETRY 2u
#define CHUNKRT_REJECT_UNKNOWN_CODE 3u
#define CHUNKRT_REJECT_OUT_OF_ORDER 4u
#define CHUNKRT_REJECT_FROM_FUTURE 5u
#define CHUNKRT_REJECT_STALE 6u
#define CHUNKRT_REJECT_OTHER 7u
#define CHUNKRT_REJECT_FOREIGN_PUBLISHER 8u /* a second writer while the bound one is alive */

/* Why the controller is in its state (ControllerStatus.state_reason, .rearm_reason). */
#define CHUNKRT_STATE_REASON_NONE 0u
#define CHUNKRT_STATE_REASON_INPUTS_GOOD 1u
#define CHUNKRT_STATE_REASON_STALE_JOINT_STATE 2u
#define CHUNKRT_STATE_REASON_NO_CHUNK 3u
#define CHUNKRT_STATE_REASON_STALE_CAMERA 4u
#define CHUNKRT_STATE_REASON_CHUNK_EXPIRED 5u
#define CHUNKRT_STATE_REASON_NON_FINITE_ACTION 6u
#define CHUNKRT_STATE_REASON_BAD_CHUNK 7u
#define CHUNKRT_STATE_REASON_OVERRUNS 8u
#define CHUNKRT_STATE_REASON_HOLD_TIMEOUT 9u
#define CHUNKRT_STATE_REASON_BAD_JOINT_STATE 10u
#define CHUNKRT_STATE_REASON_GENERATOR_ERROR 11u
#define CHUNKRT_STATE_REASON_REARM 12u
#define CHUNKRT_STATE_REASON_INFERENCE_ERROR 13u
#define CHUNKRT_STATE_REASON_NOT_OBEYED 14u
#define CHUNKRT_STATE_REASON_ROBOT_NOT_FOLLOWING 15u

/* The answer to re-arm request ControllerStatus.rearm_seq. */
#define CHUNKRT_REARM_NONE 0u
#define CHUNKRT_REARM_ACCEPTED 1u            /* FAULT -> STARTING */
#define CHUNKRT_REARM_REFUSED_NOT_IN_FAULT 2u
#define CHUNKRT_REARM_REFUSED_INPUTS 3u      /* rearm_reason: the input still bad */
/** Oldest re-arm request the controller acts on (ns). */
#define CHUNKRT_REARM_MAX_AGE_NS 1000000000ull

/** Status published by the controller. */
typedef struct ControllerStatus {
    uint64_t seq;
    uint64_t publish_time_ns;
    uint32_t state; /**< CHUNKRT_CONTROLLER_STATE_* */
    uint32_t n_dof;
    uint64_t ticks;
    uint64_t overruns;
    uint64_t chunks;
    uint64_t joint_states;
    uint64_t frames;
    uint64_t rejected[CHUNKRT_REJECT_REASON_COUNT]; /**< by CHUNKRT_REJECT_* */
    uint64_t last_inference_latency_ns;
    uint64_t lateness_p50_ns;
    uint64_t lateness_p99_ns;
    uint64_t lateness_max_ns;
    uint64_t compute_p50_ns;
    uint64_t compute_p99_ns;
    uint64_t compute_max_ns;
    uint64_t joint_state_age_ns;
    uint64_t hold_entries;
    /* bit i: camera i (configuration order) missing or older than frame_max_age_ms when the
       policy would use it; while any is set no chunk is computed and the controller holds */
    uint64_t stale_cameras;
    /* iceoryx2 unique id of the controller's joint-command publisher: [0] low 64 bits, [1] high
       64 bits (0: not known yet). Session binding: a robot obeys only commands whose sample
       publisher id equals the id announced by the status publisher it is bound to; before the
       first status, and while a second status publisher speaks, it obeys none (README
       "Isolation"; the Rust reference is chunkrt_ipc::SessionGate). */
    uint64_t command_publisher_id[2];
    uint64_t rearm_seq;     /**< seq of the last re-arm request answered (0: none) */
    uint32_t state_reason;  /**< CHUNKRT_STATE_REASON_*: why in this state */
    uint32_t rearm_result;  /**< CHUNKRT_REARM_* answer to rearm_seq */
    uint32_t rearm_reason;  /**< with CHUNKRT_REARM_REFUSED_INPUTS: CHUNKRT_STATE_REASON_* */
    uint32_t foreign_statuses; /**< statuses from another status publisher seen (saturating) */
} ControllerStatus;

/* ---- re-arm request (operator -> controller, `chunkrt rearm`) ---------------------------- */

/** Asks the controller to leave FAULT; answered in its next status. Rejected and counted:
    seq 0, reserved != 0, older than CHUNKRT_REARM_MAX_AGE_NS, from the future. */
typedef struct RearmRequest {
    uint64_t seq;             /**< non-zero id, echoed in ControllerStatus.rearm_seq */
    uint64_t publish_time_ns; /**< CLOCK_MONOTONIC */
    uint64_t reserved;        /**< zero */
} RearmRequest;

/* ---- action chunk (controller -> recorders, viewers) ------------------------------------ */

/** Most actions a published chunk carries. */
#define CHUNKRT_MAX_CHUNK_HORIZON 128

/** Every chunk the controller's chunk source delivers: what the policy predicted. Published by
    the inference thread; the control tick does nothing for it. */
typedef struct ActionChunkMsg {
    uint64_t seq;                 /**< per publisher, +1 per message */
    uint64_t publish_time_ns;     /**< CLOCK_MONOTONIC */
    uint64_t chunk_id;            /**< JointCommand.chunk_id while it executes */
    uint64_t observation_seq;     /**< JointState.seq behind the observation */
    uint64_t observation_time_ns; /**< capture time of the observation */
    uint64_t ready_time_ns;       /**< when the chunk was ready: ready - observation = latency */
    uint64_t start_shift_ns;      /**< action 0 is for observation_time_ns + start_shift_ns */
    uint64_t period_ns;           /**< between consecutive actions */
    uint32_t delay_steps;         /**< the inference delay (actions) the request was made with */
    uint32_t horizon;             /**< rows of actions used (<= CHUNKRT_MAX_CHUNK_HORIZON) */
    uint32_t n_dof;               /**< columns of actions used */
    uint32_t reserved;            /**< zero */
    double actions[CHUNKRT_MAX_CHUNK_HORIZON][CHUNKRT_MAX_DOF];
} ActionChunkMsg;

/* ---- compile-time layout checks (the full per-field check is in tests/ipc_layout.rs) ---- */

#if defined(__cplusplus)
#define CHUNKRT_STATIC_ASSERT(c, m) static_assert(c, m)
#else
#define CHUNKRT_STATIC_ASSERT(c, m) _Static_assert(c, m)
#endif
CHUNKRT_STATIC_ASSERT(sizeof(CameraFrameHeader) == 48, "CameraFrameHeader size");
CHUNKRT_STATIC_ASSERT(sizeof(JointState) == 24 + 3 * 8 * CHUNKRT_MAX_DOF + 16, "JointState size");
CHUNKRT_STATIC_ASSERT(sizeof(JointCommand) == 56 + 3 * 8 * CHUNKRT_MAX_DOF, "JointCommand size");
CHUNKRT_STATIC_ASSERT(sizeof(ControllerStatus) == 24 + 5 * 8 + 8 * CHUNKRT_REJECT_REASON_COUNT + 15 * 8,
                      "ControllerStatus size");
CHUNKRT_STATIC_ASSERT(sizeof(RearmRequest) == 24, "RearmRequest size");
CHUNKRT_STATIC_ASSERT(sizeof(ActionChunkMsg) == 80 + 8 * CHUNKRT_MAX_CHUNK_HORIZON * CHUNKRT_MAX_DOF,
                      "ActionChunkMsg size");

#ifdef __cplusplus
}
#endif

#endif /* CHUNKRT_IPC_H */
