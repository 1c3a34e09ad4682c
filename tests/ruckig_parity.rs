//! The allocation-free ruckig shim (`chunkrt_controller::control::otg`) agrees with the `ruckig` crate
//! (same C++ library, compiled separately) on random problems: same result code, same
//! duration, same sampled states; and the online `update` loops produce the same commands.

use chunkrt_controller::control::otg::{Otg, OtgInput, OtgOutput, OtgResult, OtgState};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

struct Problem {
    dofs: usize,
    p0: Vec<f64>,
    v0: Vec<f64>,
    a0: Vec<f64>,
    pf: Vec<f64>,
    vf: Vec<f64>,
    af: Vec<f64>,
    vmax: Vec<f64>,
    amax: Vec<f64>,
    jmax: Vec<f64>,
}

fn random_problem(rng: &mut ChaCha8Rng) -> Problem {
    let dofs = rng.gen_range(1..=7);
    let mut v = |lo: f64, hi: f64| (0..dofs).map(|_| rng.gen_range(lo..hi)).collect::<Vec<_>>();
    let vmax = v(0.5, 3.0);
    let amax = v(1.0, 20.0);
    let jmax = v(10.0, 1000.0);
    let p0 = v(-2.0, 2.0);
    let pf = v(-2.0, 2.0);
    let s0 = v(-0.8, 0.8);
    let s1 = v(-0.5, 0.5);
    let s2 = v(-0.3, 0.3);
    let s3 = v(-0.3, 0.3);
    let at_rest = v(0.0, 1.0); // about half of the joints start / end at rest
    let pick =
        |i: usize, s: &[f64], lim: &[f64]| if at_rest[i] < 0.5 { 0.0 } else { s[i] * lim[i] };
    let v0 = (0..dofs).map(|i| pick(i, &s0, &vmax)).collect();
    let vf = (0..dofs).map(|i| pick(i, &s1, &vmax)).collect();
    let a0 = (0..dofs).map(|i| pick(i, &s2, &amax)).collect();
    let af = (0..dofs).map(|i| pick(i, &s3, &amax)).collect();
    Problem {
        dofs,
        p0,
        v0,
        a0,
        pf,
        vf,
        af,
        vmax,
        amax,
        jmax,
    }
}

fn shim_input(p: &Problem) -> OtgInput {
    let mut i = OtgInput {
        dofs: p.dofs as u32,
        ..Default::default()
    };
    let n = p.dofs;
    i.current_position[..n].copy_from_slice(&p.p0);
    i.current_velocity[..n].copy_from_slice(&p.v0);
    i.current_acceleration[..n].copy_from_slice(&p.a0);
    i.target_position[..n].copy_from_slice(&p.pf);
    i.target_velocity[..n].copy_from_slice(&p.vf);
    i.target_acceleration[..n].copy_from_slice(&p.af);
    i.max_velocity[..n].copy_from_slice(&p.vmax);
    i.max_acceleration[..n].copy_from_slice(&p.amax);
    i.max_jerk[..n].copy_from_slice(&p.jmax);
    i
}

fn crate_input(p: &Problem) -> ruckig::InputParameter {
    let mut i = ruckig::InputParameter::new(p.dofs);
    i.current_position = p.p0.clone();
    i.current_velocity = p.v0.clone();
    i.current_acceleration = p.a0.clone();
    i.target_position = p.pf.clone();
    i.target_velocity = p.vf.clone();
    i.target_acceleration = p.af.clone();
    i.max_velocity = p.vmax.clone();
    i.max_acceleration = p.amax.clone();
    i.max_jerk = p.jmax.clone();
    i
}

fn code(r: &ruckig::Result) -> i32 {
    match r {
        ruckig::Result::Working => 0,
        ruckig::Result::Finished => 1,
        ruckig::Result::Error => -1,
        ruckig::Result::ErrorInvalidInput => -100,
        ruckig::Result::ErrorTrajectoryDuration => -101,
        ruckig::Result::ErrorPositionalLimits => -102,
        ruckig::Result::ErrorZeroLimits => -104,
        ruckig::Result::ErrorExecutionTimeCalculation => -110,
        ruckig::Result::ErrorSynchronizationCalculation => -111,
    }
}

fn shim_code(r: OtgResult) -> i32 {
    match r {
        OtgResult::Working => 0,
        OtgResult::Finished => 1,
        OtgResult::Error(e) => e,
    }
}

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol * (1.0 + a.abs().max(b.abs()))
}

/// Returns (problems solved by both, max position difference).
fn offline_sweep(n: usize, seed: u64) -> (usize, f64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut otg = Otg::new(0.001).expect("valid dt");
    let mut solved = 0;
    let mut max_diff: f64 = 0.0;
    let mut st = OtgState::default();
    for case in 0..n {
        let p = random_problem(&mut rng);
        let (r_shim, d_shim) = otg.calculate(&shim_input(&p));
        let mut rk = ruckig::Ruckig::new_direct_and_offline(p.dofs);
        let mut inp = crate_input(&p);
        let mut traj = ruckig::Trajectory::new_direct(p.dofs);
        let r_crate = rk.calculate(&mut inp, &mut traj);
        assert_eq!(
            shim_code(r_shim),
            code(&r_crate),
            "case {case}: result codes differ"
        );
        if !r_shim.is_ok() {
            continue;
        }
        solved += 1;
        let d_crate = traj.get_duration();
        assert!(
            close(d_shim, d_crate, 1e-9),
            "case {case}: duration {d_shim} vs {d_crate}"
        );
        for f in [0.0, 0.13, 0.5, 0.77, 1.0, 1.2] {
            let t = f * d_crate;
            otg.at_time(t, &mut st);
            let (pc, vc, ac) = traj.at_time(t);
            for j in 0..p.dofs {
                max_diff = max_diff.max((st.position[j] - pc[j]).abs());
                assert!(
                    close(st.position[j], pc[j], 1e-9),
                    "case {case} t={t} j={j}: p"
                );
                assert!(
                    close(st.velocity[j], vc[j], 1e-8),
                    "case {case} t={t} j={j}: v"
                );
                assert!(
                    close(st.acceleration[j], ac[j], 1e-7),
                    "case {case} t={t} j={j}: a"
                );
            }
        }
    }
    (solved, max_diff)
}

#[test]
fn shim_matches_crate_on_random_offline_problems() {
    let (solved, max_diff) = offline_sweep(3000, 7);
    eprintln!("offline parity: {solved}/3000 problems solved by both, max |dp| = {max_diff:.3e}");
    assert!(solved > 2000, "only {solved} problems were solvable");
}

#[test]
fn shim_matches_crate_online_updates() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let mut max_diff: f64 = 0.0;
    let mut cycles = 0;
    for case in 0..100 {
        let p = random_problem(&mut rng);
        let mut otg = Otg::new(0.001).expect("valid dt");
        let mut si = shim_input(&p);
        let mut so = OtgOutput::default();
        let mut rk = ruckig::Ruckig::new_direct(p.dofs, 0.001);
        let mut ci = crate_input(&p);
        let mut co = ruckig::OutputParameter::new_direct(p.dofs);
        for step in 0..300 {
            // A moving target: exercises recalculation.
            if step % 50 == 49 {
                for j in 0..p.dofs {
                    let d = 0.1 * ((step + j) as f64).sin();
                    si.target_position[j] += d;
                    ci.target_position[j] += d;
                }
            }
            let rs = otg.update(&si, &mut so);
            let rc = rk.update(&mut ci, &mut co);
            assert_eq!(shim_code(rs), code(&rc), "case {case} step {step}");
            if !rs.is_ok() {
                break;
            }
            cycles += 1;
            for j in 0..p.dofs {
                max_diff = max_diff.max((so.state.position[j] - co.new_position[j]).abs());
                assert!(
                    close(so.state.position[j], co.new_position[j], 1e-9),
                    "case {case} step {step}"
                );
                assert!(
                    close(so.state.velocity[j], co.new_velocity[j], 1e-8),
                    "case {case} step {step}"
                );
            }
            si.current_position = so.state.position;
            si.current_velocity = so.state.velocity;
            si.current_acceleration = so.state.acceleration;
            co.pass_to_input(&mut ci);
        }
    }
    eprintln!("online parity: {cycles} cycles in 100 runs, max |dp| = {max_diff:.3e}");
    assert!(cycles > 20_000);
}

#[test]
#[ignore = "large sweep (minutes); run with --ignored"]
fn shim_matches_crate_large_sweep() {
    let (solved, max_diff) = offline_sweep(100_000, 1234);
    eprintln!("offline parity: {solved}/100000 solved, max |dp| = {max_diff:.3e}");
}
