//! Where an observation's parts sit in an openpi request: which key feeds which image input,
//! the state and the prompt. openpi's robots each have their own (its `*Inputs` transforms read
//! them); [`Layout`] names them, with presets for openpi's example clients:
//!
//! | preset | images (model input ← key) | state | prompt |
//! |---|---|---|---|
//! | `chunkrt` (default) | each image input `<name>` ← `observation/<name>` (HWC) | `observation/state` | `prompt` |
//! | `libero` | `base_0_rgb` ← `observation/image`, `left_wrist_0_rgb` ← `observation/wrist_image` (HWC) | `observation/state` | `prompt` |
//! | `aloha` | `base_0_rgb` ← `images`/`cam_high`, `left_wrist_0_rgb` ← `images`/`cam_left_wrist`, `right_wrist_0_rgb` ← `images`/`cam_right_wrist` (CHW) | `state` | `prompt` |
//! | `droid` | `base_0_rgb` ← `observation/exterior_image_1_left`, `left_wrist_0_rgb` ← `observation/wrist_image_left` (HWC) | `observation/joint_position` + `observation/gripper_position` | `prompt` |
//!
//! In TOML (`[openpi]` of a robot configuration) a key is a string (a top-level key, slashes
//! and all, as openpi's LIBERO and DROID keys are) or a list of strings (a path into nested
//! maps, as ALOHA's `images`):
//!
//! ```toml
//! [openpi]
//! preset = "aloha"                    # start from a preset ...
//! state = ["observation/joint_position", "observation/gripper_position"]   # ... and override
//! [openpi.images]
//! base_0_rgb = ["images", "cam_high"]
//! ```
//!
//! Images travel as uint8 arrays, HWC or CHW (a server reads both, telling them apart by which
//! axis has 3 channels; a client sends as [`Layout::chw`] says).

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::msgpack::Value;

/// A key in a request: one top-level key, or a path into nested maps.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum KeyPath {
    /// A top-level key (it may contain slashes: `observation/image`).
    Key(String),
    /// A path of keys into nested maps: `["images", "cam_high"]`.
    Path(Vec<String>),
}

impl KeyPath {
    /// The path's segments.
    pub fn segments(&self) -> Vec<&str> {
        match self {
            KeyPath::Key(k) => vec![k.as_str()],
            KeyPath::Path(p) => p.iter().map(String::as_str).collect(),
        }
    }

    /// The value at this path in `msg`.
    pub fn find<'m, 'a>(&self, msg: &'m Value<'a>) -> Option<&'m Value<'a>> {
        self.segments().into_iter().try_fold(msg, |v, k| v.get(k))
    }
}

impl std::fmt::Display for KeyPath {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            KeyPath::Key(k) => write!(f, "{k:?}"),
            KeyPath::Path(p) => write!(f, "{}", p.join(" → ")),
        }
    }
}

/// openpi's example layouts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    /// chunkrt's own: every image input under `observation/<name>`.
    #[default]
    Chunkrt,
    /// openpi's LIBERO example client.
    Libero,
    /// openpi's ALOHA clients (nested `images`, CHW).
    Aloha,
    /// openpi's DROID example client.
    Droid,
}

impl Preset {
    /// Every preset.
    pub const ALL: [Preset; 4] = [
        Preset::Chunkrt,
        Preset::Libero,
        Preset::Aloha,
        Preset::Droid,
    ];

    /// Its name in the configuration.
    pub fn name(self) -> &'static str {
        match self {
            Preset::Chunkrt => "chunkrt",
            Preset::Libero => "libero",
            Preset::Aloha => "aloha",
            Preset::Droid => "droid",
        }
    }
}

/// `[openpi]`: the request layout. Unset fields come from the preset.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LayoutConfig {
    /// The preset the other fields override.
    #[serde(default)]
    pub preset: Preset,
    /// Image input name → key. Replaces the preset's images when given.
    #[serde(default)]
    pub images: Option<BTreeMap<String, KeyPath>>,
    /// The keys whose values, concatenated, are the state.
    #[serde(default)]
    pub state: Option<Vec<KeyPath>>,
    /// The prompt's key.
    #[serde(default)]
    pub prompt: Option<KeyPath>,
    /// Send images channel-first (a client's choice; a server reads both).
    #[serde(default)]
    pub chw: Option<bool>,
    /// Image inputs a request may leave out (masked, as openpi does with a missing wrist
    /// camera). Replaces the preset's list when given.
    #[serde(default)]
    pub optional_images: Option<Vec<String>>,
    /// What the server's actions mean for the robot (a client's choice: the robot environment
    /// the checkpoint was trained with). Default `joint_position`.
    #[serde(default)]
    pub action_space: ActionSpace,
    /// With `action_space = "droid_joint_velocity"`: the position step of a full-scale velocity
    /// action (rad; DROID's `max_joint_delta`, 0.2).
    #[serde(default)]
    pub max_joint_delta: Option<f64>,
}

/// `[openpi] action_space`: what the server's actions mean for the robot.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ActionSpace {
    /// Absolute joint positions, the robot's joints in order (openpi's ALOHA and LIBERO
    /// clients after their output transforms; chunkrt's own checkpoints).
    #[default]
    JointPosition,
    /// DROID's robot environment (`RobotEnv(action_space="joint_velocity",
    /// gripper_action_space="position")`, which openpi's DROID client drives): 7 joint
    /// velocities in [-1, 1], each a step of `max_joint_delta` (0.2 rad) at full scale from where
    /// the arm is (droid/franka/robot.py, `create_action_dict`; droid/robot_ik/robot_ik_solver.py),
    /// and the gripper's position in [0, 1] (1 closed), binarised at 0.5 (openpi's
    /// examples/droid/main.py). The state sent carries the gripper the same way (1 closed).
    DroidJointVelocity,
}

/// DROID's `max_joint_delta` (droid/robot_ik/robot_ik_solver.py): rad per full-scale action.
pub const DROID_MAX_JOINT_DELTA: f64 = 0.2;

/// The resolved layout.
#[derive(Debug, Clone, PartialEq)]
pub struct Layout {
    /// The preset it started from.
    pub preset: Preset,
    /// Image input name → key; `None`: every image input `n` under `observation/n`.
    pub images: Option<BTreeMap<String, KeyPath>>,
    /// The state's parts, in order.
    pub state: Vec<KeyPath>,
    /// The prompt.
    pub prompt: KeyPath,
    /// Images are sent channel-first.
    pub chw: bool,
    /// Image inputs a request may leave out.
    pub optional: Vec<String>,
    /// What the actions mean for the robot.
    pub action_space: ActionSpace,
    /// `DroidJointVelocity`: rad per full-scale velocity action.
    pub max_joint_delta: f64,
}

fn key(k: &str) -> KeyPath {
    KeyPath::Key(k.to_string())
}

impl Layout {
    /// A preset as it is.
    pub fn preset(p: Preset) -> Self {
        let images = |pairs: &[(&str, KeyPath)]| {
            Some(
                pairs
                    .iter()
                    .map(|(n, k)| (n.to_string(), k.clone()))
                    .collect(),
            )
        };
        let nested = |a: &str, b: &str| KeyPath::Path(vec![a.to_string(), b.to_string()]);
        match p {
            Preset::Chunkrt => Layout {
                preset: p,
                images: None,
                state: vec![key("observation/state")],
                prompt: key("prompt"),
                chw: false,
                optional: vec![],
                action_space: ActionSpace::JointPosition,
                max_joint_delta: DROID_MAX_JOINT_DELTA,
            },
            Preset::Libero => Layout {
                preset: p,
                images: images(&[
                    ("base_0_rgb", key("observation/image")),
                    ("left_wrist_0_rgb", key("observation/wrist_image")),
                ]),
                state: vec![key("observation/state")],
                prompt: key("prompt"),
                chw: false,
                optional: vec![],
                action_space: ActionSpace::JointPosition,
                max_joint_delta: DROID_MAX_JOINT_DELTA,
            },
            Preset::Aloha => Layout {
                preset: p,
                images: images(&[
                    ("base_0_rgb", nested("images", "cam_high")),
                    ("left_wrist_0_rgb", nested("images", "cam_left_wrist")),
                    ("right_wrist_0_rgb", nested("images", "cam_right_wrist")),
                ]),
                state: vec![key("state")],
                prompt: key("prompt"),
                chw: true,
                // openpi's ALOHA input transform needs only cam_high
                optional: vec!["left_wrist_0_rgb".into(), "right_wrist_0_rgb".into()],
                action_space: ActionSpace::JointPosition,
                max_joint_delta: DROID_MAX_JOINT_DELTA,
            },
            Preset::Droid => Layout {
                preset: p,
                images: images(&[
                    ("base_0_rgb", key("observation/exterior_image_1_left")),
                    ("left_wrist_0_rgb", key("observation/wrist_image_left")),
                ]),
                state: vec![
                    key("observation/joint_position"),
                    key("observation/gripper_position"),
                ],
                prompt: key("prompt"),
                chw: false,
                optional: vec![],
                action_space: ActionSpace::JointPosition,
                max_joint_delta: DROID_MAX_JOINT_DELTA,
            },
        }
    }

    /// The layout a configuration section describes.
    pub fn from_config(c: &LayoutConfig) -> Result<Self, String> {
        let mut l = Self::preset(c.preset);
        if let Some(images) = &c.images {
            l.images = Some(images.clone());
        }
        if let Some(state) = &c.state {
            if state.is_empty() {
                return Err("openpi.state: at least one key".into());
            }
            l.state = state.clone();
        }
        if let Some(p) = &c.prompt {
            l.prompt = p.clone();
        }
        if let Some(chw) = c.chw {
            l.chw = chw;
        }
        if let Some(o) = &c.optional_images {
            l.optional = o.clone();
        }
        l.action_space = c.action_space;
        if let Some(d) = c.max_joint_delta {
            if !(d.is_finite() && d > 0.0 && d <= 1.0) {
                return Err(format!(
                    "openpi.max_joint_delta {d}: must be within (0, 1] rad"
                ));
            }
            l.max_joint_delta = d;
        }
        for k in l
            .images
            .iter()
            .flat_map(|m| m.values())
            .chain(&l.state)
            .chain([&l.prompt])
        {
            let segs = k.segments();
            if segs.is_empty() || segs.iter().any(|s| s.is_empty() || s.len() > 256) {
                return Err(format!(
                    "openpi: key {k} must be 1..=256 characters per segment"
                ));
            }
        }
        Ok(l)
    }

    /// The key of image input `name` (`None`: this layout does not carry it).
    pub fn image_key(&self, name: &str) -> Option<KeyPath> {
        match &self.images {
            None => Some(KeyPath::Key(format!("observation/{name}"))),
            Some(m) => m.get(name).cloned(),
        }
    }
}

impl Default for Layout {
    fn default() -> Self {
        Self::preset(Preset::Chunkrt)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgpack::{decode, Limits, Writer};

    #[test]
    fn presets_and_overrides_from_toml() {
        let c: LayoutConfig = toml::from_str(
            r#"
            preset = "aloha"
            state = ["observation/joint_position", "observation/gripper_position"]
            [images]
            base_0_rgb = ["images", "top"]
            "#,
        )
        .unwrap();
        let l = Layout::from_config(&c).unwrap();
        assert!(l.chw);
        assert_eq!(
            l.image_key("base_0_rgb"),
            Some(KeyPath::Path(vec!["images".into(), "top".into()]))
        );
        assert_eq!(l.image_key("left_wrist_0_rgb"), None);
        assert_eq!(l.state.len(), 2);
        assert_eq!(
            Layout::default().image_key("wrist"),
            Some(key("observation/wrist"))
        );
        assert!(toml::from_str::<LayoutConfig>("preset = \"nope\"").is_err());
        assert!(toml::from_str::<LayoutConfig>("statee = \"x\"").is_err());
        let empty = LayoutConfig {
            state: Some(vec![]),
            ..Default::default()
        };
        assert!(Layout::from_config(&empty).is_err());
    }

    #[test]
    fn paths_find_nested_values() {
        let mut w = Writer::new();
        w.map(2)
            .str("images")
            .map(1)
            .str("cam_high")
            .str("x")
            .str("observation/state")
            .str("y");
        let v = decode(&w.buf, Limits::default()).unwrap();
        let aloha = Layout::preset(Preset::Aloha);
        let k = aloha.image_key("base_0_rgb").unwrap();
        assert_eq!(k.find(&v), Some(&Value::Str("x")));
        assert_eq!(key("observation/state").find(&v), Some(&Value::Str("y")));
        assert_eq!(key("observation").find(&v), None);
    }
}
