//! `cargo bench --bench control_loop [-- --quick]`: control-thread wake-up lateness and tick
//! compute at 500 Hz / 1 kHz, idle and under a candle matmul load, vs cyclictest.
//! See `chunkrt_bench::control_loop`. The tick body is the controller's executor tick
//! (`ControllerTick`: `ControlLoop::step` with its iceoryx2 ports, the executor, ruckig).

mod common;

use chunkrt_bench::control_loop::{self, Options};

fn main() {
    common::single_threaded_candle();
    common::main("control_loop", |opts| {
        control_loop::run(&Options::new(opts)).map(|_| ())
    });
}
