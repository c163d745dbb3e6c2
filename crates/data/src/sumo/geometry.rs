//! Polyline offsets: lane surfaces from centre lines and widths, lane boundaries for dividers.

/// Rounds every coordinate of a network to 1 cm, SUMO's own precision, which keeps network files short.
pub fn round_network(net: &mut umgen_scene::RoadNetwork) {
    let r = |v: &mut f64| *v = (*v * 100.0).round() / 100.0;
    let poly = |p: &mut Vec<[f64; 2]>| p.iter_mut().flatten().for_each(r);
    net.lanes
        .iter_mut()
        .chain(&mut net.connectors)
        .chain(&mut net.intersections)
        .chain(&mut net.sidewalks)
        .for_each(poly);
    net.crosswalks.iter_mut().for_each(|c| poly(&mut c.polygon));
    net.stop_lines
        .iter_mut()
        .chain(&mut net.dividers)
        .for_each(|m| poly(&mut m.line));
}

/// Drops consecutive duplicate points.
pub fn dedup(line: &[[f64; 2]]) -> Vec<[f64; 2]> {
    let mut out: Vec<[f64; 2]> = Vec::with_capacity(line.len());
    for p in line {
        if out.last().is_none_or(|q| (q[0] - p[0]).hypot(q[1] - p[1]) > 1e-6) {
            out.push(*p);
        }
    }
    out
}

fn left_normal(a: [f64; 2], b: [f64; 2]) -> [f64; 2] {
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let n = dx.hypot(dy);
    [-dy / n, dx / n]
}

/// The polyline shifted `d` metres to its left (negative: right), with mitred joints whose length is
/// capped at three times `d` so that sharp turns do not spike.
pub fn offset(line: &[[f64; 2]], d: f64) -> Vec<[f64; 2]> {
    let line = dedup(line);
    if line.len() < 2 {
        return line;
    }
    let last = line.len() - 1;
    (0..line.len())
        .map(|i| {
            let n = if i == 0 {
                left_normal(line[0], line[1])
            } else if i == last {
                left_normal(line[last - 1], line[last])
            } else {
                let (n0, n1) = (
                    left_normal(line[i - 1], line[i]),
                    left_normal(line[i], line[i + 1]),
                );
                let m = [n0[0] + n1[0], n0[1] + n1[1]];
                let len = m[0].hypot(m[1]);
                if len < 1e-9 {
                    n0
                } else {
                    let m = [m[0] / len, m[1] / len];
                    let scale = (1.0 / (m[0] * n0[0] + m[1] * n0[1])).min(3.0);
                    [m[0] * scale, m[1] * scale]
                }
            };
            [line[i][0] + n[0] * d, line[i][1] + n[1] * d]
        })
        .collect()
}

/// The surface of a lane: its centre line widened to `width`.
pub fn strip(line: &[[f64; 2]], width: f64) -> Vec<[f64; 2]> {
    let mut poly = offset(line, width / 2.0);
    let mut right = offset(line, -width / 2.0);
    right.reverse();
    poly.extend(right);
    poly
}

/// Unit direction from the first to the last point (`[1, 0]` when they coincide).
pub fn direction(line: &[[f64; 2]]) -> [f64; 2] {
    match (line.first(), line.last()) {
        (Some(a), Some(b)) if (b[0] - a[0]).hypot(b[1] - a[1]) > 1e-9 => {
            let n = (b[0] - a[0]).hypot(b[1] - a[1]);
            [(b[0] - a[0]) / n, (b[1] - a[1]) / n]
        }
        _ => [1.0, 0.0],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn straight_lane_strip_is_a_rectangle() {
        let p = strip(&[[0.0, 0.0], [10.0, 0.0], [10.0, 0.0]], 3.2);
        assert_eq!(p, vec![[0.0, 1.6], [10.0, 1.6], [10.0, -1.6], [0.0, -1.6]]);
    }

    #[test]
    fn right_angle_offsets_meet_at_the_mitre() {
        // Left turn: (0,0) → (10,0) → (10,10); 1 m to the left the corner is at (9, 1).
        let o = offset(&[[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]], 1.0);
        assert!(
            (o[1][0] - 9.0).abs() < 1e-9 && (o[1][1] - 1.0).abs() < 1e-9,
            "{o:?}"
        );
        assert_eq!(direction(&[[0.0, 0.0], [0.0, 5.0]]), [0.0, 1.0]);
    }
}
