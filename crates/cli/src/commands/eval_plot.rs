//! The pictures of `umgen eval`: L2 and the scene's statistics over the horizon.

use std::path::Path;
use umgen_viz::{Rgb, text, write_png};

/// Curves of ego and agent L2 (model solid colours, constant velocity lighter) over the horizon, as a PNG.
pub fn l2_plot(rows: &[serde_json::Value], path: &Path) -> anyhow::Result<()> {
    write_png(path, &l2_picture(rows))?;
    Ok(())
}

/// The picture of [`l2_plot`].
fn l2_picture(rows: &[serde_json::Value]) -> Rgb {
    let series = [
        ("ego_model", [200, 40, 40], "EGO MODEL"),
        ("ego_constant_velocity", [240, 160, 160], "EGO CV"),
        ("agents_model", [40, 80, 200], "AGENTS MODEL"),
        ("agents_constant_velocity", [150, 170, 240], "AGENTS CV"),
    ];
    curves(rows, &series, "L2 (M) OVER HORIZON")
}

/// Agents per frame, entries and exits per second of the rollouts over the horizon (solid) against the
/// real split's (the same colours lighter, flat), as a PNG; nothing without horizon rows.
pub fn horizon_plot(horizon: &serde_json::Value, path: &Path) -> anyhow::Result<()> {
    if let Some(img) = horizon_picture(horizon) {
        write_png(path, &img)?;
    }
    Ok(())
}

/// The picture of [`horizon_plot`].
fn horizon_picture(horizon: &serde_json::Value) -> Option<Rgb> {
    let seconds = horizon["seconds"].as_array().filter(|r| r.len() >= 2)?;
    let keys = ["agents_mean", "entries_per_s", "exits_per_s"];
    let rows: Vec<serde_json::Value> = seconds
        .iter()
        .map(|r| {
            let mut row = serde_json::json!({"seconds": r["second"]});
            for k in keys {
                row[k] = r["generated"][k].clone();
                row[format!("{k}_real")] = horizon["real"][k].clone();
            }
            row
        })
        .collect();
    let series = [
        ("agents_mean", [40, 80, 200], "AGENTS / FRAME"),
        ("agents_mean_real", [150, 170, 240], "REAL"),
        ("entries_per_s", [30, 150, 60], "ENTRIES / S"),
        ("entries_per_s_real", [150, 215, 160], "REAL"),
        ("exits_per_s", [200, 40, 40], "EXITS / S"),
        ("exits_per_s_real", [240, 160, 160], "REAL"),
    ];
    Some(curves(&rows, &series, "SCENE OVER HORIZON"))
}

/// Curves of `series` (key, colour, legend) of `rows` (each with `seconds`) on a 480 × 320 picture, the
/// largest value at the top, with a legend and the horizon's range.
fn curves(rows: &[serde_json::Value], series: &[(&str, [u8; 3], &str)], title: &str) -> Rgb {
    let (w, h, m) = (480usize, 320usize, 40.0);
    let mut img = Rgb::filled(w, h, [255, 255, 255]);
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
        // A swatch of the curve's colour, then the name in white on the label's darkened box (the
        // light colours do not read on the dark box themselves).
        let y = 6.0 + 12.0 * s as f64 + 5.0;
        img.line([w as f64 - 172.0, y], [w as f64 - 156.0, y], 3.0, *colour);
        text(&mut img, 6 + 12 * s, w - 150, 1, label, [255, 255, 255]);
    }
    let secs = |r: Option<&serde_json::Value>| r.and_then(|r| r["seconds"].as_f64()).unwrap_or(0.0);
    text(
        &mut img,
        h - 30,
        m as usize,
        1,
        &format!("HORIZON {:.1} TO {:.1} S", secs(rows.first()), secs(rows.last())),
        [255, 255, 255],
    );
    text(
        &mut img,
        6,
        46,
        1,
        &format!("{title}, MAX {top:.2}"),
        [255, 255, 255],
    );
    img
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn the_plot_has_a_swatch_per_series_and_the_curves_reach_the_top() {
        let rows: Vec<serde_json::Value> = (1..=4)
            .map(|h| {
                serde_json::json!({"horizon": h, "seconds": 0.5 * h as f64, "ego_model": 1.0 * h as f64,
                    "ego_constant_velocity": 0.5, "agents_model": 8.0, "agents_constant_velocity": null})
            })
            .collect();
        let img = l2_picture(&rows);
        if let Some(p) = std::env::var_os("UMGEN_KEEP_PLOT") {
            write_png(Path::new(&p), &img).unwrap();
        }
        let (w, h) = (img.width, img.height);
        assert_eq!((w, h), (480, 320));
        let px = |c: usize, r: usize| img.pixels[r * w + c];
        // Swatches at the legend rows, in the series' colours.
        for (s, colour) in [[200, 40, 40], [240, 160, 160], [40, 80, 200], [150, 170, 240]]
            .iter()
            .enumerate()
        {
            assert_eq!(px(w - 164, 6 + 12 * s + 5), *colour, "swatch {s}");
        }
        // The largest value (agents, 8 m) is drawn at the top margin (y = 40), in the agents' colour.
        assert!((36..=44).any(|y| px(240, y) == [40, 80, 200]));
    }

    #[test]
    fn the_horizon_plot_draws_the_rollout_and_the_real_level() {
        let seconds: Vec<serde_json::Value> = (1..=3)
            .map(|s| {
                serde_json::json!({"second": s, "generated": {"agents_mean": 10.0 - 3.0 * s as f64,
                    "entries_per_s": 1.0, "exits_per_s": null}})
            })
            .collect();
        let horizon = serde_json::json!({"seconds": seconds,
            "real": {"agents_mean": 10.0, "entries_per_s": 2.0, "exits_per_s": 2.0}});
        let img = horizon_picture(&horizon).unwrap();
        let w = img.width;
        let px = |c: usize, r: usize| img.pixels[r * w + c];
        // The real agents' level (10, the largest value) runs along the top margin across the plot; the
        // rollout's agents start there and fall to 1 at the right (y = 40 + 240 · 0.9 = 256).
        assert!((36..=44).any(|y| px(400, y) == [150, 170, 240]));
        assert!((252..=260).any(|y| px(438, y) == [40, 80, 200]));
        assert!(horizon_picture(&serde_json::json!({"seconds": [], "real": {}})).is_none());
    }
}
