// Allocation-free C shim over ruckig (see chunkrt_ruckig.h).
//
// Built by chunkrt's build.rs with `-Druckig=chunkrt_ruckig_impl` (a private namespace) and
// without WITH_CLOUD_CLIENT: only the local (non-cloud) calculator is compiled.
#include "chunkrt_ruckig.h"

#include <atomic>
#include <cstdlib>
#include <new>

#include <ruckig/ruckig.hpp>

namespace {

constexpr size_t N = CHUNKRT_RK_MAX_DOF;
using Rk = ruckig::Ruckig<N>;
using In = ruckig::InputParameter<N>;
using Out = ruckig::OutputParameter<N>;
using Traj = ruckig::Trajectory<N>;

std::atomic<uint64_t> g_cxx_allocations{0};

void fill_input(const chunkrt_rk_input& src, In& in) {
    const size_t dofs = src.dofs;
    in.control_interface = src.control_interface == 1 ? ruckig::ControlInterface::Velocity
                                                      : ruckig::ControlInterface::Position;
    switch (src.synchronization) {
        case 1: in.synchronization = ruckig::Synchronization::TimeIfNecessary; break;
        case 2: in.synchronization = ruckig::Synchronization::Phase; break;
        case 3: in.synchronization = ruckig::Synchronization::None; break;
        default: in.synchronization = ruckig::Synchronization::Time; break;
    }
    for (size_t i = 0; i < N; ++i) {
        const bool on = i < dofs;
        in.enabled[i] = on;
        in.current_position[i] = on ? src.current_position[i] : 0.0;
        in.current_velocity[i] = on ? src.current_velocity[i] : 0.0;
        in.current_acceleration[i] = on ? src.current_acceleration[i] : 0.0;
        in.target_position[i] = on ? src.target_position[i] : 0.0;
        in.target_velocity[i] = on ? src.target_velocity[i] : 0.0;
        in.target_acceleration[i] = on ? src.target_acceleration[i] : 0.0;
        in.max_velocity[i] = on ? src.max_velocity[i] : 1.0;
        in.max_acceleration[i] = on ? src.max_acceleration[i] : 1.0;
        in.max_jerk[i] = on ? src.max_jerk[i] : 1.0;
    }
    // Position limits (infinite: no limit); unused joints get none.
    for (size_t i = 0; i < N; ++i) {
        const bool on = i < dofs;
        in.min_position[i] = on ? src.min_position[i] : -std::numeric_limits<double>::infinity();
        in.max_position[i] = on ? src.max_position[i] : std::numeric_limits<double>::infinity();
    }
}

void copy_state(const Out& o, chunkrt_rk_state& s) {
    for (size_t i = 0; i < N; ++i) {
        s.position[i] = o.new_position[i];
        s.velocity[i] = o.new_velocity[i];
        s.acceleration[i] = o.new_acceleration[i];
        s.jerk[i] = o.new_jerk[i];
    }
}

}  // namespace

struct chunkrt_rk_handle {
    Rk rk;
    In in;
    Out out;
    Traj traj;
    explicit chunkrt_rk_handle(double dt) : rk(dt) {}
};

extern "C" {

chunkrt_rk_handle* chunkrt_rk_new(double delta_time) {
    if (!(delta_time > 0.0) || !std::isfinite(delta_time)) {
        return nullptr;
    }
    return new (std::nothrow) chunkrt_rk_handle(delta_time);
}

void chunkrt_rk_free(chunkrt_rk_handle* h) { delete h; }

void chunkrt_rk_reset(chunkrt_rk_handle* h) {
    if (h) {
        h->rk.reset();
    }
}

int32_t chunkrt_rk_update(chunkrt_rk_handle* h, const chunkrt_rk_input* in, chunkrt_rk_output* out) {
    if (!h || !in || !out || in->dofs == 0 || in->dofs > N) {
        return static_cast<int32_t>(ruckig::Result::ErrorInvalidInput);
    }
    fill_input(*in, h->in);
    const auto r = h->rk.update(h->in, h->out);
    copy_state(h->out, out->state);
    out->time = h->out.time;
    out->duration = h->out.trajectory.get_duration();
    out->new_calculation = h->out.new_calculation ? 1 : 0;
    return static_cast<int32_t>(r);
}

int32_t chunkrt_rk_calculate(chunkrt_rk_handle* h, const chunkrt_rk_input* in, double* duration) {
    if (!h || !in || in->dofs == 0 || in->dofs > N) {
        return static_cast<int32_t>(ruckig::Result::ErrorInvalidInput);
    }
    fill_input(*in, h->in);
    const auto r = h->rk.calculate(h->in, h->traj);
    if (duration) {
        *duration = h->traj.get_duration();
    }
    return static_cast<int32_t>(r);
}

void chunkrt_rk_at_time(const chunkrt_rk_handle* h, double time, chunkrt_rk_state* out) {
    if (!h || !out) {
        return;
    }
    std::array<double, N> p{}, v{}, a{}, j{};
    size_t section = 0;
    h->traj.at_time(time, p, v, a, j, section);
    for (size_t i = 0; i < N; ++i) {
        out->position[i] = p[i];
        out->velocity[i] = v[i];
        out->acceleration[i] = a[i];
        out->jerk[i] = j[i];
    }
}

uint64_t chunkrt_rk_cxx_allocations(void) { return g_cxx_allocations.load(std::memory_order_relaxed); }

}  // extern "C"

// Counting replacements of the global allocation functions: every C++ allocation in the process
// (ruckig, libstdc++) is counted, so tests can prove the control tick allocates nothing.
namespace {
void* counted_alloc(std::size_t n) {
    g_cxx_allocations.fetch_add(1, std::memory_order_relaxed);
    void* p = std::malloc(n == 0 ? 1 : n);
    return p;
}
void* counted_aligned_alloc(std::size_t n, std::align_val_t al) {
    g_cxx_allocations.fetch_add(1, std::memory_order_relaxed);
    void* p = nullptr;
    const std::size_t a = static_cast<std::size_t>(al) < sizeof(void*) ? sizeof(void*) : static_cast<std::size_t>(al);
    if (posix_memalign(&p, a, n == 0 ? 1 : n) != 0) {
        return nullptr;
    }
    return p;
}
}  // namespace

void* operator new(std::size_t n) {
    void* p = counted_alloc(n);
    if (!p) throw std::bad_alloc();
    return p;
}
void* operator new[](std::size_t n) {
    void* p = counted_alloc(n);
    if (!p) throw std::bad_alloc();
    return p;
}
void* operator new(std::size_t n, const std::nothrow_t&) noexcept { return counted_alloc(n); }
void* operator new[](std::size_t n, const std::nothrow_t&) noexcept { return counted_alloc(n); }
void* operator new(std::size_t n, std::align_val_t al) {
    void* p = counted_aligned_alloc(n, al);
    if (!p) throw std::bad_alloc();
    return p;
}
void* operator new[](std::size_t n, std::align_val_t al) {
    void* p = counted_aligned_alloc(n, al);
    if (!p) throw std::bad_alloc();
    return p;
}
void* operator new(std::size_t n, std::align_val_t al, const std::nothrow_t&) noexcept { return counted_aligned_alloc(n, al); }
void* operator new[](std::size_t n, std::align_val_t al, const std::nothrow_t&) noexcept { return counted_aligned_alloc(n, al); }
void operator delete(void* p) noexcept { std::free(p); }
void operator delete[](void* p) noexcept { std::free(p); }
void operator delete(void* p, std::size_t) noexcept { std::free(p); }
void operator delete[](void* p, std::size_t) noexcept { std::free(p); }
void operator delete(void* p, const std::nothrow_t&) noexcept { std::free(p); }
void operator delete[](void* p, const std::nothrow_t&) noexcept { std::free(p); }
void operator delete(void* p, std::align_val_t) noexcept { std::free(p); }
void operator delete[](void* p, std::align_val_t) noexcept { std::free(p); }
void operator delete(void* p, std::size_t, std::align_val_t) noexcept { std::free(p); }
void operator delete[](void* p, std::size_t, std::align_val_t) noexcept { std::free(p); }
void operator delete(void* p, std::align_val_t, const std::nothrow_t&) noexcept { std::free(p); }
void operator delete[](void* p, std::align_val_t, const std::nothrow_t&) noexcept { std::free(p); }
