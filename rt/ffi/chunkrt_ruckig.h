// chunkrt_ruckig: a minimal, allocation-free C interface over ruckig's C++ API.
//
// One handle owns a fixed-size `Ruckig<CHUNKRT_RK_MAX_DOF>` (std::array storage, no
// std::vector), its input and its output. Joints beyond `dofs` are disabled (`enabled = false`)
// and never take part in the calculation or the time synchronisation.
// Only `chunkrt_rk_new` / `chunkrt_rk_free` allocate; every other call is allocation-free.
// The library is compiled with `-Druckig=chunkrt_ruckig_impl`, so its C++ symbols never clash
// with the copy of ruckig that the `ruckig` crate links (lib `ruckig`).
#pragma once

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define CHUNKRT_RK_MAX_DOF 16

// Flat input of one update / calculation (SI units). Infinite position limits disable them.
typedef struct chunkrt_rk_input {
    uint32_t dofs;               // 1..=CHUNKRT_RK_MAX_DOF
    int32_t control_interface;   // 0: position, 1: velocity
    int32_t synchronization;     // 0: time, 1: time if necessary, 2: phase, 3: none
    int32_t reserved;
    double current_position[CHUNKRT_RK_MAX_DOF];
    double current_velocity[CHUNKRT_RK_MAX_DOF];
    double current_acceleration[CHUNKRT_RK_MAX_DOF];
    double target_position[CHUNKRT_RK_MAX_DOF];
    double target_velocity[CHUNKRT_RK_MAX_DOF];
    double target_acceleration[CHUNKRT_RK_MAX_DOF];
    double max_velocity[CHUNKRT_RK_MAX_DOF];
    double max_acceleration[CHUNKRT_RK_MAX_DOF];
    double max_jerk[CHUNKRT_RK_MAX_DOF];
    double min_position[CHUNKRT_RK_MAX_DOF];
    double max_position[CHUNKRT_RK_MAX_DOF];
} chunkrt_rk_input;

// Kinematic state at one instant.
typedef struct chunkrt_rk_state {
    double position[CHUNKRT_RK_MAX_DOF];
    double velocity[CHUNKRT_RK_MAX_DOF];
    double acceleration[CHUNKRT_RK_MAX_DOF];
    double jerk[CHUNKRT_RK_MAX_DOF];
} chunkrt_rk_state;

// Output of `chunkrt_rk_update`.
typedef struct chunkrt_rk_output {
    chunkrt_rk_state state;       // the state one delta_time later
    double time;                  // time on the current trajectory (s)
    double duration;              // duration of the current trajectory (s)
    int32_t new_calculation;      // 1 when this update computed a new trajectory
    int32_t reserved;
} chunkrt_rk_output;

typedef struct chunkrt_rk_handle chunkrt_rk_handle;

// Creates a generator with cycle time `delta_time` (s); NULL on bad arguments or no memory.
chunkrt_rk_handle* chunkrt_rk_new(double delta_time);
// Frees a generator (NULL is ignored).
void chunkrt_rk_free(chunkrt_rk_handle* h);
// Forces a new calculation at the next update.
void chunkrt_rk_reset(chunkrt_rk_handle* h);
// Online update (ruckig's `update`): returns ruckig's `Result` code (0 working, 1 finished, <0 error).
int32_t chunkrt_rk_update(chunkrt_rk_handle* h, const chunkrt_rk_input* in, chunkrt_rk_output* out);
// Offline calculation (ruckig's `calculate`) into the handle's trajectory; `duration` receives its length.
int32_t chunkrt_rk_calculate(chunkrt_rk_handle* h, const chunkrt_rk_input* in, double* duration);
// Samples the trajectory of the last `chunkrt_rk_calculate` at `time` (s).
void chunkrt_rk_at_time(const chunkrt_rk_handle* h, double time, chunkrt_rk_state* out);
// Number of C++ `operator new` calls in this process since start (all libraries).
uint64_t chunkrt_rk_cxx_allocations(void);

#ifdef __cplusplus
}
#endif
