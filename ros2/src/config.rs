//! The bridge's view of a robot's configuration file: the shared sections (chunkrt-ipc's checks)
//! and `[ros2]` ([`chunkrt_ipc::config::ros2`], where its types live so that the controller reads
//! the same file).

use std::path::Path;

use chunkrt_ipc::config::{read_config_file, Checker, ConfigError, SharedConfig};
use serde::Deserialize;

pub use chunkrt_ipc::config::ros2::*;

/// The whole file as the bridge reads it.
#[derive(Debug, Clone)]
pub struct BridgeConfig {
    pub shared: SharedConfig,
    pub ros2: Ros2Config,
}

/// The `[ros2]` section only (the rest of the file is not read here).
#[derive(Deserialize)]
struct Ros2Only {
    #[serde(default)]
    ros2: Option<Ros2Config>,
}

impl BridgeConfig {
    /// Reads `path`: the shared sections (chunkrt-ipc's checks) and `[ros2]` (this crate's; an
    /// absent section is all defaults).
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let file = path.display().to_string();
        let shared = SharedConfig::load(path)?;
        let text = read_config_file(path)?;
        Self::from_parts(shared, &text, &file)
    }

    /// Parses `[ros2]` from `text` (the file `file` whose shared sections are `shared`).
    pub fn from_parts(shared: SharedConfig, text: &str, file: &str) -> Result<Self, ConfigError> {
        let only: Ros2Only = toml::from_str(text).map_err(|e| ConfigError::Parse {
            file: file.to_string(),
            message: e.to_string().trim_end().to_string(),
        })?;
        let mut ros2 = only.ros2.unwrap_or_default();
        ros2.finish(&shared, &Checker { file })?;
        Ok(Self { shared, ros2 })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(extra: &str) -> Result<BridgeConfig, ConfigError> {
        let text = format!("{}\n{extra}", chunkrt_ipc::config::DEFAULT_TOML);
        let shared = SharedConfig::parse(&text, "t.toml")?;
        BridgeConfig::from_parts(shared, &text, "t.toml")
    }

    #[test]
    fn defaults_follow_ros2_control() {
        let c = parse("").unwrap().ros2;
        assert_eq!(c.joints, ["shoulder", "elbow", "wrist", "gripper"]);
        assert_eq!(c.command_topic, "/forward_position_controller/commands");
        assert_eq!(c.state_qos, QosKind::SensorData);
        assert_eq!(c.command_qos, QosKind::Reliable);
        let t = parse("[ros2]\ncommand = \"trajectory\"").unwrap().ros2;
        assert_eq!(
            t.command_topic,
            "/joint_trajectory_controller/joint_trajectory"
        );
    }

    #[test]
    fn errors_name_the_key() {
        let e = |s: &str| parse(s).unwrap_err().to_string();
        assert!(e("[ros2]\njoints = [\"a\", \"b\"]").contains("ros2.joints"));
        assert!(e("[ros2]\njoints = [\"a\", \"a\", \"b\", \"c\"]").contains("ros2.joints[1]"));
        assert!(e("[ros2]\ndomain_id = 300").contains("ros2.domain_id"));
        assert!(e("[ros2]\njoint_states_topic = \"joint_states\"").contains("joint_states_topic"));
        assert!(e("[ros2]\ncommand = \"velocity\"").contains("velocity"));
        assert!(e("[ros2]\nbogus = 1").contains("bogus"));
    }
}
