//! `fake-camera`: publishes deterministic synthetic frames on one service per camera.
//!
//! Every frame is a function of (seed, camera id, frame seq): a horizontal gradient moving with
//! the frame number (red), a vertical gradient (green) and a seeded 8×8-block pattern (blue),
//! converted to the camera's encoding. The frame number is burned in twice: the first 8 bytes
//! of row 0 hold `seq` little-endian (machine-readable, see [`read_seq_stamp`]) and rows 1..5
//! show its low 16 bits as black / white bars.
//!
//! One thread serves all cameras from one schedule of absolute deadlines; frames are rendered
//! straight into the loaned shared-memory sample (no copy, no allocation per frame).

use std::sync::atomic::Ordering;

use chunkrt_ipc::config::CameraConfig;
use chunkrt_ipc::services;
use chunkrt_ipc::*;
use rand::{Rng, SeedableRng};

use crate::common::{check_rate, end_time_ns, open_node, sleep_until_or_stop, CommonArgs};
use crate::scene::ReachScene;
use crate::shutdown;

/// Command-line arguments.
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub common: CommonArgs,
    /// Cameras to publish, comma separated (default: every camera of the configuration). A name
    /// not in the configuration gets `--width`×`--height` (default 224×224), rgb8.
    #[arg(long, value_name = "NAME,...", value_delimiter = ',')]
    pub cameras: Option<Vec<String>>,
    /// Frame rate of every camera (default: each camera's `fps`).
    #[arg(long, value_name = "HZ")]
    pub fps: Option<f64>,
    /// Frame width of every camera (default: the configured width).
    #[arg(long)]
    pub width: Option<u32>,
    /// Frame height of every camera (default: the configured height).
    #[arg(long)]
    pub height: Option<u32>,
    /// Seed of the synthetic pattern.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Stop after this many seconds (default: run until SIGINT / SIGTERM).
    #[arg(long, value_name = "SECONDS")]
    pub duration: Option<f64>,
    /// What the frames show: `pattern` (the stamped test pattern) or `reach` (the reach task's
    /// arm and targets, rendered from the robot's joint states; rgb8 cameras only).
    #[arg(long, value_name = "SCENE", default_value = "pattern", value_parser = ["pattern", "reach"])]
    pub scene: String,
    /// Episode seed of the reach scene (places the targets).
    #[arg(long, value_name = "SEED", default_value_t = 0)]
    pub scene_seed: u64,
}

impl Default for Args {
    /// The same values as an empty command line.
    fn default() -> Self {
        Self {
            common: CommonArgs::default(),
            cameras: None,
            fps: None,
            width: None,
            height: None,
            seed: 0,
            duration: None,
            scene: "pattern".to_string(),
            scene_seed: 0,
        }
    }
}

/// Geometry and encoding of one camera's frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameFormat {
    pub width: u32,
    pub height: u32,
    /// Bytes per row (here always `width × bytes per pixel`).
    pub stride: u32,
    /// `ENCODING_*` code.
    pub encoding: u32,
}

impl FrameFormat {
    /// Packed rows of a known encoding; `None` for an unknown code or a zero size.
    pub fn packed(width: u32, height: u32, encoding: u32) -> Option<Self> {
        let bpp = bytes_per_pixel(encoding)?;
        if width == 0 || height == 0 {
            return None;
        }
        Some(Self {
            width,
            height,
            stride: width.checked_mul(bpp)?,
            encoding,
        })
    }

    /// Payload bytes of one frame.
    pub fn bytes(&self) -> usize {
        self.stride as usize * self.height as usize
    }
}

/// The seeded part of a camera's image: one byte per pixel, constant over 8×8 blocks.
pub fn seeded_pattern(seed: u64, camera_id: u32, width: u32, height: u32) -> Vec<u8> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(
        seed ^ (camera_id as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15),
    );
    let bw = width.div_ceil(8) as usize;
    let bh = height.div_ceil(8) as usize;
    let blocks: Vec<u8> = (0..bw * bh).map(|_| rng.gen()).collect();
    let mut out = vec![0u8; width as usize * height as usize];
    for y in 0..height as usize {
        for x in 0..width as usize {
            out[y * width as usize + x] = blocks[(y / 8) * bw + x / 8];
        }
    }
    out
}

/// Renders frame `seq` into `buf` (`format.bytes()` long) from the camera's `pattern`
/// (`width × height` bytes from [`seeded_pattern`]).
pub fn render_frame(buf: &mut [u8], format: &FrameFormat, pattern: &[u8], seq: u64) {
    let w = format.width as usize;
    let h = format.height as usize;
    let stride = format.stride as usize;
    let bpp = bytes_per_pixel(format.encoding).unwrap_or(1) as usize;
    if buf.len() < stride * h || pattern.len() < w * h {
        return;
    }
    let shift = (seq.wrapping_mul(4) & 0xff) as usize;
    for y in 0..h {
        let g = (y * 256 / h) as u8;
        let row = &mut buf[y * stride..y * stride + w * bpp];
        for x in 0..w {
            let r = ((x * 256 / w + shift) & 0xff) as u8;
            let b = pattern[y * w + x];
            let px = &mut row[x * bpp..(x + 1) * bpp];
            match format.encoding {
                ENCODING_RGB8 => px.copy_from_slice(&[r, g, b]),
                ENCODING_BGR8 => px.copy_from_slice(&[b, g, r]),
                _ => px[0] = ((r as u16 + 2 * g as u16 + b as u16) / 4) as u8,
            }
        }
    }
    // Bars: the low 16 bits of seq, most significant first, in rows 1..5.
    for y in 1..h.min(5) {
        let row = &mut buf[y * stride..y * stride + w * bpp];
        for x in 0..w {
            let bit = 15 - (x * 16 / w);
            let v = if (seq >> bit) & 1 == 1 { 255 } else { 0 };
            row[x * bpp..(x + 1) * bpp].fill(v);
        }
    }
    // Machine-readable stamp at the start of row 0.
    let n = stride.min(8);
    buf[..n].copy_from_slice(&seq.to_le_bytes()[..n]);
}

/// The frame seq stamped into a frame's first 8 bytes; `None` if the frame is shorter.
pub fn read_seq_stamp(payload: &[u8]) -> Option<u64> {
    let bytes: [u8; 8] = payload.get(..8)?.try_into().ok()?;
    Some(u64::from_le_bytes(bytes))
}

/// One camera to publish.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraPlan {
    pub name: String,
    pub camera_id: u32,
    pub fps: f64,
    pub format: FrameFormat,
    /// Largest payload the publisher must hold.
    pub max_bytes: usize,
}

/// Which cameras to publish, with which format, from the configuration and the overrides.
pub fn plan(cameras: &[CameraConfig], args: &Args) -> anyhow::Result<Vec<CameraPlan>> {
    let names: Vec<String> = match &args.cameras {
        Some(list) => list.clone(),
        None => cameras.iter().map(|c| c.name.clone()).collect(),
    };
    anyhow::ensure!(
        !names.is_empty(),
        "no cameras: the configuration has none and --cameras was not given"
    );
    let mut out: Vec<CameraPlan> = Vec::new();
    let mut extra_id = cameras.len() as u32;
    for name in names {
        anyhow::ensure!(
            !name.is_empty()
                && name.len() <= 64
                && name
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-'),
            "camera name {name:?}: must be 1..=64 characters of [A-Za-z0-9_-]"
        );
        anyhow::ensure!(
            !out.iter().any(|p| p.name == name),
            "camera {name:?} listed twice"
        );
        let (id, cfg) = match cameras.iter().position(|c| c.name == name) {
            Some(i) => (i as u32, cameras[i].clone()),
            None => {
                extra_id += 1;
                (
                    extra_id - 1,
                    CameraConfig {
                        name: name.clone(),
                        width: 224,
                        height: 224,
                        fps: 30.0,
                        encoding: "rgb8".to_string(),
                    },
                )
            }
        };
        let width = args.width.unwrap_or(cfg.width);
        let height = args.height.unwrap_or(cfg.height);
        anyhow::ensure!(
            (1..=8192).contains(&width) && (1..=8192).contains(&height),
            "camera {name}: {width}x{height}: width and height must be in 1..=8192"
        );
        let fps = check_rate("--fps", args.fps.unwrap_or(cfg.fps), 0.1, 1000.0)?;
        let encoding = cfg.encoding_code();
        let format = FrameFormat::packed(width, height, encoding)
            .ok_or_else(|| anyhow::anyhow!("camera {name}: bad format"))?;
        let configured = FrameFormat::packed(cfg.width, cfg.height, encoding)
            .map(|f| f.bytes())
            .unwrap_or(0);
        out.push(CameraPlan {
            name,
            camera_id: id,
            fps,
            format,
            max_bytes: configured.max(format.bytes()),
        });
    }
    Ok(out)
}

/// Frames published per camera, printed on exit.
#[derive(Debug, Clone, PartialEq)]
pub struct Summary {
    /// `(camera name, frames published)`.
    pub frames: Vec<(String, u64)>,
    /// Frames that could not be loaned or sent.
    pub failures: u64,
}

impl std::fmt::Display for Summary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "fake-camera summary:")?;
        for (name, n) in &self.frames {
            write!(f, " {name}={n}")?;
        }
        write!(f, " failures={}", self.failures)
    }
}

/// Runs until SIGINT / SIGTERM or `--duration`; prints the [`Summary`] on stdout.
pub fn run(args: Args) -> anyhow::Result<()> {
    let summary = publish(&args)?;
    println!("{summary}");
    Ok(())
}

/// The whole process: returns the counters instead of printing them.
pub fn publish(args: &Args) -> anyhow::Result<Summary> {
    let stop = shutdown::flag();
    let (cfg, ns) = args.common.load()?;
    let plans = plan(&cfg.cameras, args)?;
    let node = open_node("chunkrt-fake-camera")?;
    // The reach scene follows the robot: the newest valid joint state (initially the
    // configured initial positions).
    let scene = match args.scene.as_str() {
        "reach" => {
            for p in &plans {
                anyhow::ensure!(
                    p.format.encoding == ENCODING_RGB8,
                    "camera {}: the reach scene renders rgb8 only",
                    p.name
                );
            }
            anyhow::ensure!(
                cfg.n_dof() >= 3,
                "the reach scene needs an arm of at least 3 joints, the configuration has {}",
                cfg.n_dof()
            );
            let service = services::joint_state_service(&node, &ns.joint_state())?;
            let sub = services::subscriber(&service)?;
            tracing::info!("fake-camera: reach scene, episode seed {}", args.scene_seed);
            Some((ReachScene::from_seed(args.scene_seed), sub))
        }
        _ => None,
    };
    let mut q = [0.0f64; MAX_DOF];
    for (i, j) in cfg.robot.joints.iter().enumerate().take(MAX_DOF) {
        q[i] = j.initial_position;
    }
    let n_dof = cfg.n_dof().min(MAX_DOF);

    struct Live {
        plan: CameraPlan,
        pattern: Vec<u8>,
        publisher: iceoryx2::port::publisher::Publisher<services::Ipc, [u8], CameraFrameHeader>,
        period_ns: u64,
        next_ns: u64,
        seq: u64,
    }
    let start = monotonic_ns();
    let end = end_time_ns(start, args.duration)?;
    let mut cams = Vec::with_capacity(plans.len());
    for p in plans {
        let name = ns.camera(&p.name);
        let service = services::camera_service(&node, &name)?;
        let publisher = services::camera_publisher(&service, p.max_bytes)?;
        tracing::info!(
            "fake-camera: '{name}' id {} {}x{} {} at {} fps",
            p.camera_id,
            p.format.width,
            p.format.height,
            encoding_name(p.format.encoding),
            p.fps
        );
        cams.push(Live {
            pattern: seeded_pattern(args.seed, p.camera_id, p.format.width, p.format.height),
            period_ns: (1e9 / p.fps).round() as u64,
            next_ns: start,
            seq: 0,
            publisher,
            plan: p,
        });
    }

    let mut failures = 0u64;
    while !stop.load(Ordering::Relaxed) {
        // The camera whose frame is due first.
        let Some(i) = (0..cams.len()).min_by_key(|&i| cams[i].next_ns) else {
            break;
        };
        let due = cams[i].next_ns;
        if due >= end {
            break;
        }
        if !sleep_until_or_stop(due, stop) {
            break;
        }
        if let Some((_, sub)) = &scene {
            while let Ok(Some(s)) = sub.receive() {
                let m = s.payload();
                if m.n_dof as usize == n_dof && validate_joint_state(m, None).is_ok() {
                    q[..n_dof].copy_from_slice(&m.position[..n_dof]);
                }
            }
        }
        let cam = &mut cams[i];
        let capture = monotonic_ns();
        let f = cam.plan.format;
        match cam.publisher.loan_slice(f.bytes()) {
            Ok(mut sample) => {
                cam.seq += 1;
                match &scene {
                    Some((sc, _)) => sc.render_rgb(
                        &q[..n_dof],
                        f.width as usize,
                        f.height as usize,
                        f.stride as usize,
                        sample.payload_mut(),
                    ),
                    None => render_frame(sample.payload_mut(), &f, &cam.pattern, cam.seq),
                }
                *sample.user_header_mut() = CameraFrameHeader {
                    seq: cam.seq,
                    capture_time_ns: capture,
                    publish_time_ns: monotonic_ns(),
                    camera_id: cam.plan.camera_id,
                    encoding: f.encoding,
                    width: f.width,
                    height: f.height,
                    stride: f.stride,
                    reserved: 0,
                };
                if let Err(e) = sample.send() {
                    failures += 1;
                    if failures <= 10 {
                        tracing::warn!("fake-camera: {}: send failed: {e:?}", cam.plan.name);
                    }
                }
            }
            Err(e) => {
                failures += 1;
                if failures <= 10 {
                    tracing::warn!("fake-camera: {}: loan failed: {e:?}", cam.plan.name);
                }
            }
        }
        cam.next_ns += cam.period_ns;
        let now = monotonic_ns();
        if now > cam.next_ns + 10 * cam.period_ns {
            // Far behind: restart the schedule instead of bursting.
            cam.next_ns = now;
        }
    }
    tracing::info!("fake-camera: stopping");
    Ok(Summary {
        frames: cams.iter().map(|c| (c.plan.name.clone(), c.seq)).collect(),
        failures,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_args_match_the_empty_command_line() {
        use clap::Parser;
        #[derive(clap::Parser)]
        struct Cli {
            #[command(flatten)]
            args: Args,
        }
        assert_eq!(Cli::parse_from(["fake-camera"]).args, Args::default());
    }

    #[test]
    fn frames_are_deterministic_stamped_and_encoded() {
        let f = FrameFormat::packed(32, 16, ENCODING_RGB8).unwrap();
        let pat = seeded_pattern(7, 0, 32, 16);
        assert_eq!(pat, seeded_pattern(7, 0, 32, 16));
        assert_ne!(pat, seeded_pattern(8, 0, 32, 16));
        assert_ne!(pat, seeded_pattern(7, 1, 32, 16));
        let mut a = vec![0u8; f.bytes()];
        let mut b = vec![0u8; f.bytes()];
        render_frame(&mut a, &f, &pat, 0x0102_0304_0506_0708);
        render_frame(&mut b, &f, &pat, 0x0102_0304_0506_0708);
        assert_eq!(a, b);
        assert_eq!(read_seq_stamp(&a), Some(0x0102_0304_0506_0708));
        // blue of pixel (5, 10) is the pattern
        let px = 10 * f.stride as usize + 5 * 3;
        assert_eq!(a[px + 2], pat[10 * 32 + 5]);
        // the bar of bit 3 (set in ..0708) is white, bit 4 is black (row 2)
        let bit_x = |bit: usize| (15 - bit) * 32 / 16;
        assert_eq!(a[2 * f.stride as usize + bit_x(3) * 3], 255);
        assert_eq!(a[2 * f.stride as usize + bit_x(4) * 3], 0);
        // BGR swaps red and blue
        let fb = FrameFormat {
            encoding: ENCODING_BGR8,
            ..f
        };
        render_frame(&mut b, &fb, &pat, 1);
        render_frame(&mut a, &f, &pat, 1);
        assert_eq!(a[px], b[px + 2]);
        assert_eq!(a[px + 2], b[px]);
        // mono: one byte per pixel
        let fm = FrameFormat::packed(32, 16, ENCODING_MONO8).unwrap();
        assert_eq!(fm.stride, 32);
        let mut m = vec![0u8; fm.bytes()];
        render_frame(&mut m, &fm, &pat, 9);
        assert_eq!(read_seq_stamp(&m), Some(9));
    }

    #[test]
    fn plan_applies_overrides_and_rejects_bad_names() {
        let cfg = chunkrt_ipc::SharedConfig::embedded_default();
        let mut args = Args {
            common: CommonArgs::default(),
            cameras: None,
            fps: Some(50.0),
            width: Some(64),
            height: None,
            seed: 0,
            duration: None,
            scene: "pattern".to_string(),
            scene_seed: 0,
        };
        let p = plan(&cfg.cameras, &args).unwrap();
        assert_eq!(p.len(), cfg.cameras.len());
        let last = cfg.cameras.len() - 1;
        assert_eq!(p[last].camera_id, last as u32);
        assert_eq!(p[last].format.width, 64);
        assert_eq!(p[last].format.height, cfg.cameras[last].height);
        assert_eq!(p[0].fps, 50.0);
        args.cameras = Some(vec!["extra".into()]);
        let p = plan(&cfg.cameras, &args).unwrap();
        assert_eq!(p[0].camera_id, cfg.cameras.len() as u32);
        assert_eq!(p[0].format.height, 224);
        args.cameras = Some(vec!["bad name".into()]);
        assert!(plan(&cfg.cameras, &args).is_err());
        args.cameras = None;
        args.fps = Some(0.0);
        assert!(plan(&cfg.cameras, &args).is_err());
    }
}
