//! Delayed views: image inputs that show an earlier frame of a live camera
//! ([`chunkrt_policy::DelayedView`]). A policy that sees the newest frame and one taken
//! `delay_ms` before it can tell which way the scene moves; one frame cannot.
//!
//! Each view keeps a ring of its camera's frames, preallocated at start-up. A frame enters the
//! ring only when it is at least `delay / (slots - 2)` newer than the last one that did, so the
//! ring spans the delay whatever the camera's rate; the view then shows the newest frame in the
//! ring taken at least `delay` before the camera's newest (right after start-up, while no frame
//! is that old yet, the oldest one). Frames are copied only when they enter the ring or the view
//! changes: nothing is allocated once the rings exist.

use crate::config::Config;
use chunkrt_ipc::CameraFrameHeader;
use chunkrt_policy::DelayedView;

use super::Frame;

/// Frames a view's ring holds.
pub const RING_SLOTS: usize = 22;

struct Slot {
    header: CameraFrameHeader,
    data: Vec<u8>,
}

struct ViewRing {
    /// Index of the live camera in the configuration.
    camera: usize,
    delay_ns: u64,
    /// Least capture-time step between two frames in the ring.
    spacing_ns: u64,
    slots: Vec<Slot>,
    /// Next slot to write; `len` slots hold frames (the oldest at `next - len`).
    next: usize,
    len: usize,
    /// Capture time of the camera frame last looked at (0: none yet).
    seen_ns: u64,
    /// Capture time of the frame the view shows (0: none yet).
    shown_ns: u64,
}

/// The delayed views of an observation (see the module documentation).
pub struct FrameHistory {
    views: Vec<ViewRing>,
    /// Cameras in the configuration: view `v` is frame `cameras + v` of the observation.
    cameras: usize,
}

impl FrameHistory {
    /// Rings for `views`, each an earlier frame of one of `cfg`'s cameras. An error names a view
    /// whose camera the configuration does not have.
    pub fn new(cfg: &Config, views: &[DelayedView]) -> anyhow::Result<Self> {
        let mut rings = Vec::with_capacity(views.len());
        for v in views {
            let camera = cfg
                .cameras
                .iter()
                .position(|c| c.name == v.camera)
                .ok_or_else(|| {
                    anyhow::anyhow!(
                        "the policy's image input {:?} is camera {:?} {} ms earlier, and the \
                         configuration has no camera {:?} (its cameras: {})",
                        v.name,
                        v.camera,
                        v.delay_ms,
                        v.camera,
                        cfg.cameras
                            .iter()
                            .map(|c| c.name.as_str())
                            .collect::<Vec<_>>()
                            .join(", ")
                    )
                })?;
            anyhow::ensure!(
                !cfg.cameras.iter().any(|c| c.name == v.name),
                "the policy's image input {:?} is a delayed view of camera {:?}, and the \
                 configuration also has a live camera of that name",
                v.name,
                v.camera
            );
            let c = &cfg.cameras[camera];
            let bytes = Frame::capacity(c.width, c.height);
            rings.push(ViewRing {
                camera,
                delay_ns: v.delay_ns(),
                spacing_ns: v.delay_ns() / (RING_SLOTS as u64 - 2),
                slots: (0..RING_SLOTS)
                    .map(|_| Slot {
                        header: CameraFrameHeader::default(),
                        data: vec![0; bytes],
                    })
                    .collect(),
                next: 0,
                len: 0,
                seen_ns: 0,
                shown_ns: 0,
            });
        }
        Ok(Self {
            views: rings,
            cameras: cfg.cameras.len(),
        })
    }

    /// Takes the cameras' newest frames (`frames[..cameras]`, as [`super::CameraInput::poll`]
    /// leaves them) into the rings and sets each view's frame (`frames[cameras + v]`). No
    /// allocation.
    pub fn update(&mut self, frames: &mut [Frame]) {
        let (live, views) = frames.split_at_mut(self.cameras.min(frames.len()));
        for (ring, view) in self.views.iter_mut().zip(views.iter_mut()) {
            let Some(src) = live.get(ring.camera).filter(|f| f.valid) else {
                continue;
            };
            let t = src.header.capture_time_ns;
            if t == ring.seen_ns {
                continue;
            }
            ring.seen_ns = t;
            let newest = ring.newest_ns();
            if ring.len == 0 || t >= newest.saturating_add(ring.spacing_ns) {
                let slot = &mut ring.slots[ring.next];
                let px = src.pixels();
                slot.data[..px.len()].copy_from_slice(px);
                slot.header = src.header;
                ring.next = (ring.next + 1) % RING_SLOTS;
                ring.len = (ring.len + 1).min(RING_SLOTS);
            }
            let pick = ring.pick(t.saturating_sub(ring.delay_ns));
            let slot = &ring.slots[pick];
            if slot.header.capture_time_ns != ring.shown_ns || !view.valid {
                let n = slot.header.stride as usize * slot.header.height as usize;
                view.data[..n].copy_from_slice(&slot.data[..n]);
                view.header = slot.header;
                view.valid = true;
                ring.shown_ns = slot.header.capture_time_ns;
            }
        }
    }
}

impl ViewRing {
    fn slot(&self, age: usize) -> usize {
        (self.next + RING_SLOTS - 1 - age) % RING_SLOTS
    }

    fn newest_ns(&self) -> u64 {
        if self.len == 0 {
            0
        } else {
            self.slots[self.slot(0)].header.capture_time_ns
        }
    }

    /// The newest slot captured at or before `at_ns`; the oldest when none is that old.
    fn pick(&self, at_ns: u64) -> usize {
        (0..self.len)
            .map(|age| self.slot(age))
            .find(|&i| self.slots[i].header.capture_time_ns <= at_ns)
            .unwrap_or_else(|| self.slot(self.len.saturating_sub(1)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::edge::Observation;

    fn cfg() -> Config {
        Config::embedded_default()
    }

    fn view(delay_ms: f64) -> DelayedView {
        DelayedView {
            name: "base_0_rgb_prev".into(),
            camera: "base_0_rgb".into(),
            delay_ms,
        }
    }

    /// Camera 0 delivers a frame at `t_ms` whose pixels all read `value`.
    fn deliver(obs: &mut Observation, t_ms: u64, value: u8) {
        let f = &mut obs.frames[0];
        f.header.capture_time_ns = t_ms * 1_000_000;
        f.header.width = 64;
        f.header.height = 64;
        f.header.stride = 192;
        f.header.seq += 1;
        f.data[..192 * 64].fill(value);
        f.valid = true;
    }

    #[test]
    fn the_view_shows_the_frame_taken_the_delay_earlier() {
        let c = cfg();
        let views = [view(400.0)];
        let mut h = FrameHistory::new(&c, &views).unwrap();
        let mut obs = Observation::with_views(&c, &views);
        assert_eq!(obs.frames.len(), 2);
        assert_eq!(obs.frames[1].name, "base_0_rgb_prev");
        // 30 fps for two seconds; the pixel value is the frame's index
        for k in 0..60u64 {
            deliver(&mut obs, 1_000 + k * 100 / 3, k as u8);
            h.update(&mut obs.frames);
            let view = &obs.frames[1];
            assert!(view.valid);
            let age_ms =
                (obs.frames[0].header.capture_time_ns - view.header.capture_time_ns) / 1_000_000;
            if k * 100 / 3 >= 420 {
                // at least the delay, at most the delay plus one ring spacing and a frame
                assert!(
                    (400..=400 + 20 + 34).contains(&age_ms),
                    "frame {k}: {age_ms} ms"
                );
            } else {
                // the oldest frame while none is old enough: the first one
                assert_eq!(view.data[0], 0, "frame {k}");
            }
            assert_eq!(
                view.data[0] as u64,
                ((view.header.capture_time_ns / 1_000_000 - 1_000) * 3).div_ceil(100),
                "the view's pixels belong to its header"
            );
        }
    }

    #[test]
    fn a_fast_camera_still_reaches_back_the_whole_delay() {
        let c = cfg();
        let views = [view(400.0)];
        let mut h = FrameHistory::new(&c, &views).unwrap();
        let mut obs = Observation::with_views(&c, &views);
        // 1 kHz for one second: far more frames than slots
        for k in 0..1_000u64 {
            deliver(&mut obs, 5_000 + k, (k % 251) as u8);
            h.update(&mut obs.frames);
        }
        let age_ms = (obs.frames[0].header.capture_time_ns - obs.frames[1].header.capture_time_ns)
            / 1_000_000;
        assert!((400..=420).contains(&age_ms), "{age_ms} ms");
    }

    #[test]
    fn a_view_of_a_camera_the_configuration_lacks_is_a_clear_error() {
        let mut v = view(400.0);
        v.camera = "wrist".into();
        let e = FrameHistory::new(&cfg(), &[v]).err().expect("refused");
        let msg = format!("{e:#}");
        assert!(
            msg.contains("no camera \"wrist\"") && msg.contains("base_0_rgb"),
            "{msg}"
        );
    }
}
