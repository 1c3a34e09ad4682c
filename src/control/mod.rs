//! The control tick: turns action chunks into a smooth, limit-respecting command stream.
//! (Chunk executor, interpolation, transitions, ruckig, safety state machine, measurement.)
