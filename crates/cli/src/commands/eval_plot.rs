//! The L2-over-horizon picture of `umgen eval`.

use std::path::Path;
use umgen_viz::{Rgb, text, write_png};

/// Curves of ego and agent L2 (model solid colours, constant velocity darker) over the horizon.
pub fn l2_plot(rows: &[serde_json::Value], path: &Path) -> anyhow::Result<()> {
    let (w, h, m) = (480usize, 320usize, 40.0);
    let mut img = Rgb::filled(w, h, [255, 255, 255]);
    let series = [
        ("ego_model", [200, 40, 40], "EGO MODEL"),
        ("ego_constant_velocity", [240, 160, 160], "EGO CV"),
        ("agents_model", [40, 80, 200], "AGENTS MODEL"),
        ("agents_constant_velocity", [150, 170, 240], "AGENTS CV"),
    ];
    let top = rows
        .iter()
        .flat_map(|r| series.iter().filter_map(move |(k, _, _)| r[*k].as_f64()))
        .fold(0.0f64, f64::max)
        .max(1e-6);
    let n = rows.len().max(2) - 1;
    let at = |i: usize, v: f64| {
        [
            m + (w as f64 - 2.0 * m) * i as f64 / n as f64,
            h as f64 - m - (h as f64 - 2.0 * m) * v / top,
        ]
    };
    img.line([m, h as f64 - m], [w as f64 - m, h as f64 - m], 1.0, [0, 0, 0]);
    img.line([m, m], [m, h as f64 - m], 1.0, [0, 0, 0]);
    for (s, (key, colour, label)) in series.iter().enumerate() {
        let pts: Vec<[f64; 2]> = rows
            .iter()
            .enumerate()
            .filter_map(|(i, r)| r[*key].as_f64().map(|v| at(i, v)))
            .collect();
        for p in pts.windows(2) {
            img.line(p[0], p[1], 2.0, *colour);
        }
        text(&mut img, 6 + 12 * s, w - 150, 1, label, *colour);
    }
    text(
        &mut img,
        6,
        46,
        1,
        &format!("L2 (M) OVER HORIZON, MAX {top:.2}"),
        [0, 0, 0],
    );
    write_png(path, &img)?;
    Ok(())
}
