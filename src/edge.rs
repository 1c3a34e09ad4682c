//! The IPC edge.
