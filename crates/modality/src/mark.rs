//! [`Mark`]: what a modality draws on the bird's-eye view of a frame, so that pictures show content the
//! built-in drawing does not know about (a plug-in's traffic lights, say).

/// A shape in the ego's frame (x forward, y left, metres) that `umgen viz` draws over the map and agents.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Mark {
    /// A straight stroke from `from` to `to`.
    Line {
        /// Start (m).
        from: [f64; 2],
        /// End (m).
        to: [f64; 2],
        /// Stroke width (m).
        width: f64,
        /// RGB colour.
        colour: [u8; 3],
    },
    /// A filled disc.
    Dot {
        /// Centre (m).
        at: [f64; 2],
        /// Radius (m).
        radius: f64,
        /// RGB colour.
        colour: [u8; 3],
    },
}
