//! `chunkrt rearm`: asks the controller of a namespace to leave FAULT without a restart, and
//! prints its answer. The request (`RearmRequest` on `NS/rearm`) is repeated every 100 ms until
//! the controller's status echoes its id, or the timeout passes.
//!
//! Exit status 0: re-armed (the controller goes to STARTING, then RUNNING once its inputs are
//! good and a chunk arrives). Non-zero with the reason: refused (not in FAULT, or an input is
//! still bad: which one), or no controller answered.

use std::time::Duration;

use chunkrt_ipc::services;
use chunkrt_ipc::{
    controller_state_name, monotonic_ns, rearm_result_name, state_reason_name, ControllerStatus,
    RearmRequest, REARM_ACCEPTED, REARM_REFUSED_INPUTS,
};

use crate::common::{open_node, CommonArgs};

/// `rearm` options.
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub common: CommonArgs,
    /// Give up when no controller answered within this many seconds.
    #[arg(long, default_value_t = 3.0, value_name = "S")]
    pub timeout: f64,
}

/// What the controller answered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Answer {
    /// `REARM_*` code.
    pub result: u32,
    /// `STATE_REASON_*` of the bad input (with `REARM_REFUSED_INPUTS`).
    pub reason: u32,
    /// The controller's state in the answering status.
    pub state: u32,
}

impl std::fmt::Display for Answer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", rearm_result_name(self.result))?;
        if self.result == REARM_REFUSED_INPUTS {
            write!(f, " ({})", state_reason_name(self.reason))?;
        }
        write!(
            f,
            "; controller state: {}",
            controller_state_name(self.state)
        )
    }
}

/// Sends one re-arm request and waits for the answer.
pub fn request(args: &Args) -> anyhow::Result<Answer> {
    if !(args.timeout.is_finite() && (0.0..=600.0).contains(&args.timeout)) {
        anyhow::bail!("--timeout {}: must be 0..=600 seconds", args.timeout);
    }
    let (_cfg, ns) = args.common.load()?;
    let node = open_node("chunkrt-rearm")?;
    let rearm = services::rearm_service(&node, &ns.rearm())?;
    let publisher = services::publisher(&rearm)?;
    let status = services::status_service(&node, &ns.status())?;
    let subscriber = services::subscriber(&status)?;
    // an id that another client (or this one, earlier) is unlikely to have used
    let seq = (monotonic_ns() ^ (u64::from(std::process::id()) << 40)) | 1;
    let start = monotonic_ns();
    let end = start + (args.timeout * 1e9) as u64;
    let mut next_send = start;
    loop {
        let now = monotonic_ns();
        if now >= end {
            anyhow::bail!(
                "no controller answered on {} within {} s (is `chunkrt run` running there?)",
                ns.as_str(),
                args.timeout
            );
        }
        if now >= next_send {
            let req = RearmRequest {
                seq,
                publish_time_ns: monotonic_ns(),
                reserved: 0,
            };
            publisher.send_copy(req)?;
            next_send = now + 100_000_000;
        }
        while let Some(sample) = subscriber.receive()? {
            let st: &ControllerStatus = sample.payload();
            if st.rearm_seq == seq {
                return Ok(Answer {
                    result: st.rearm_result,
                    reason: st.rearm_reason,
                    state: st.state,
                });
            }
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Runs the tool: prints the answer; an error unless it was accepted.
pub fn run(args: Args) -> anyhow::Result<()> {
    let answer = request(&args)?;
    if answer.result == REARM_ACCEPTED {
        println!("re-armed: {answer}");
        Ok(())
    } else {
        anyhow::bail!("re-arm {answer}")
    }
}
