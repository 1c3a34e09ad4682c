//! The configuration's enums: each names its values as the TOML spells them, and an unknown
//! value is a load error that lists the allowed set. The sections that own enums (the
//! controller's `[execution]`) declare them with [`config_enum!`](crate::config_enum).

/// An enum of the configuration: serde by its TOML names (an unknown value is a load error that
/// lists the allowed set), `name()`, `Display`, and `FromStr` with the allowed set in the error.
/// The crate that uses it depends on serde.
#[macro_export]
macro_rules! config_enum {
    (
        $(#[$m:meta])*
        pub enum $name:ident ($what:literal) {
            $( $(#[$vm:meta])* $var:ident = $s:literal, )+
        }
    ) => {
        $(#[$m])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, ::serde::Serialize, ::serde::Deserialize)]
        pub enum $name {
            $( $(#[$vm])* #[serde(rename = $s)] $var, )+
        }

        impl $name {
            /// Every value, in the order the documentation lists them.
            pub const ALL: &'static [$name] = &[$($name::$var),+];

            /// The name in the configuration.
            pub fn name(&self) -> &'static str {
                match self {
                    $( $name::$var => $s, )+
                }
            }

            /// The allowed names, comma-separated (for errors and help).
            pub fn allowed() -> String {
                [$($s),+].join(", ")
            }
        }

        impl std::fmt::Display for $name {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str(self.name())
            }
        }

        impl std::str::FromStr for $name {
            type Err = String;
            fn from_str(s: &str) -> Result<Self, String> {
                match s {
                    $( $s => Ok($name::$var), )+
                    _ => Err(format!("{} {s:?}: must be one of {}", $what, Self::allowed())),
                }
            }
        }
    };
}
