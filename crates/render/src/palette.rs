//! Colours of the camera view.

use umgen_scene::AgentCategory;

/// What covers a patch of ground, in drawing order (later classes paint over earlier ones).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Class {
    /// Anything that is not road or sidewalk.
    Grass,
    /// Sidewalks and walking areas.
    Sidewalk,
    /// Lanes, connectors and junctions.
    Road,
    /// Pedestrian crossings.
    Crosswalk,
    /// Lane dividers and stop lines.
    Marking,
}

/// Ground beyond the rendered texture.
pub const FAR_GROUND: [u8; 3] = [92, 112, 80];

/// Base colour of a ground class.
pub fn ground(class: Class, stripe: bool) -> [u8; 3] {
    match class {
        Class::Grass => [78, 110, 64],
        Class::Sidewalk => [158, 156, 148],
        Class::Road => [72, 72, 78],
        Class::Crosswalk if stripe => [226, 226, 220],
        Class::Crosswalk => [72, 72, 78],
        Class::Marking => [232, 232, 225],
    }
}

/// Blends towards the horizon haze; `t` is distance over the maximum distance.
pub fn fog(rgb: [u8; 3], t: f64) -> [u8; 3] {
    const HAZE: [f64; 3] = [182.0, 196.0, 212.0];
    let a = ((t - 0.3) / 0.7).clamp(0.0, 1.0);
    [0, 1, 2].map(|k| (f64::from(rgb[k]) * (1.0 - a) + HAZE[k] * a).round() as u8)
}

/// Sky colour for a ray with vertical component `dz` (≥ 0 above the horizon).
pub fn sky(dz: f64) -> [u8; 3] {
    let a = dz.clamp(0.0, 0.5) / 0.5;
    let (low, high) = ([190.0, 205.0, 222.0], [110.0, 160.0, 225.0]);
    [0, 1, 2].map(|k| (low[k] * (1.0 - a) + high[k] * a) as u8)
}

/// Body colour of an agent box.
pub fn agent(c: AgentCategory) -> [u8; 3] {
    match c {
        AgentCategory::Vehicle => [48, 96, 200],
        AgentCategory::Pedestrian => [214, 58, 48],
        AgentCategory::Cyclist => [236, 156, 32],
    }
}

/// Lambert shading of a face with outward normal `n` under a light from above, behind the camera and to
/// the left, so that the faces the camera sees are lit.
pub fn shade(rgb: [u8; 3], n: [f64; 3]) -> [u8; 3] {
    const L: [f64; 3] = [-0.42, 0.3, 0.86];
    let lambert = (n[0] * L[0] + n[1] * L[1] + n[2] * L[2]).max(0.0);
    let k = 0.42 + 0.58 * lambert;
    rgb.map(|v| (f64::from(v) * k).round().min(255.0) as u8)
}
