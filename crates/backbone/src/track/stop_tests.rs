//! The follow rule's stop points (`TrackSpec::stops`) against hand-worked cases.

use super::*;
use burn::tensor::TensorData;

type F = burn::backend::Flex;

/// Lights-like stop slots: x, y (1 m bins over ±64 m), heading (128 bins), state `128 + code` (0 off,
/// 1 red, 2 yellow, 3 green), pad 132.
fn stops() -> StopSpec {
    StopSpec {
        segment: 1,
        slot: 4,
        values: 128,
        fields: [
            (0, (-64.0, 64.0, 128)),
            (1, (-64.0, 64.0, 128)),
            (2, (-PI, PI, 128)),
        ],
        state: 3,
        stop: vec![129],
        go: vec![130, 131],
        gap_m: StopSpec::GAP_M,
    }
}

const RED: i64 = 129;
const GREEN: i64 = 131;
const PAD: [i64; 4] = [132; 4];

fn track() -> TrackSpec {
    TrackSpec {
        segment: 0,
        slot: 6,
        values: 1024,
        fields: [
            (0, (-64.0, 64.0, 1024)),
            (1, (-64.0, 64.0, 1024)),
            (2, (-20.0, 20.0, 1024)),
            (3, (-20.0, 20.0, 1024)),
            (4, (-PI, PI, 1024)),
        ],
        step_s: 0.5,
        pad: Some(1027),
        accel: false,
        follow: Some(FollowSpec::default()),
        stops: Some(stops()),
    }
}

fn bin((lo, hi, n): (f64, f64, u32), v: f64) -> i64 {
    ((v - lo) / ((hi - lo) / f64::from(n))).floor() as i64
}

fn centre_of((lo, hi, n): (f64, f64, u32), id: i64) -> f64 {
    lo + (id as f64 + 0.5) * (hi - lo) / f64::from(n)
}

/// A head at (x, y) facing `h`, showing `state`.
fn head(x: f64, y: f64, h: f64, state: i64) -> [i64; 4] {
    let f = stops().fields;
    [bin(f[0].1, x), bin(f[1].1, y), bin(f[2].1, h), state]
}

/// The moved slots of one car at the origin driving along +x at 10 m/s, with `heads` as the stop
/// segment, under `k`.
fn run(heads: &[[i64; 4]], k: &TrackSpec) -> Vec<i64> {
    let f = k.fields;
    let car = vec![
        bin(f[0].1, 0.06),
        bin(f[1].1, 0.06),
        bin(f[2].1, 10.0),
        bin(f[3].1, 0.0),
        bin(f[4].1, 0.0),
        1024,
    ];
    let dev = Default::default();
    let m = heads.len();
    moved::<F>(
        Tensor::from_data(TensorData::new(car, [1, 1, 6]), &dev),
        Some(Tensor::from_data(
            TensorData::new(heads.concat(), [1, 1, 4 * m]),
            &dev,
        )),
        Tensor::from_data(TensorData::new(vec![0.0f32; 3], [1, 1, 3]), &dev),
        k,
    )
    .into_data()
    .iter::<i64>()
    .collect()
}

#[test]
fn a_slot_brakes_to_stop_before_a_red_line_ahead_in_its_lane() {
    let k = track();
    let free = run(&[PAD], &k);
    let red = run(&[head(20.0, 0.3, 0.0, RED)], &k);
    // From the bins' centres: v² / (2 (along − 3 m)) ≈ 2.9 m/s², 1.5 m/s less over the step.
    let f = k.fields;
    let v = centre_of(f[2].1, bin(f[2].1, 10.0));
    let line = centre_of(stops().fields[0].1, bin(stops().fields[0].1, 20.0));
    let x0 = centre_of(f[0].1, bin(f[0].1, 0.06));
    let need = v * v / (2.0 * (line - x0 - StopSpec::GAP_M));
    assert!((need - 2.9).abs() < 0.2, "{need}");
    let slower = v - 0.5 * need;
    assert_eq!(red[2], bin(f[2].1, slower));
    assert_eq!(red[0], bin(f[0].1, x0 + 0.5 * (v + slower) / 2.0));
    assert!(free[2] - red[2] >= 30, "{} against {}", red[2], free[2]);
    // Without the stop points the same frame keeps its speed.
    assert_eq!(
        run(
            &[head(20.0, 0.3, 0.0, RED)],
            &TrackSpec {
                stops: None,
                ..k.clone()
            }
        ),
        free
    );
}

#[test]
fn a_red_line_green_for_another_movement_behind_beside_or_facing_away_stops_nobody() {
    let k = track();
    let free = run(&[PAD], &k);
    let cases: [(&str, Vec<[i64; 4]>); 6] = [
        (
            "green at the same line",
            vec![head(20.0, 0.3, 0.0, RED), head(20.2, 0.4, 0.0, GREEN)],
        ),
        ("green line beside it", vec![head(20.0, 0.3, 0.0, GREEN)]),
        ("red behind", vec![head(-15.0, 0.3, 0.0, RED)]),
        ("red in the next lane", vec![head(20.0, 3.5, 0.0, RED)]),
        ("red for the crossing road", vec![head(20.0, 0.3, PI / 2.0, RED)]),
        ("red too far to need the onset", vec![head(60.0, 0.3, 0.0, RED)]),
    ];
    for (what, heads) in cases {
        assert_eq!(run(&heads, &k), free, "{what}");
    }
    // A red line at another lane end beside a green one still stops.
    let two = run(&[head(20.0, 0.3, 0.0, RED), head(20.0, 3.5, 0.0, GREEN)], &k);
    assert_ne!(two, free);
    assert_eq!(two, run(&[head(20.0, 0.3, 0.0, RED)], &k));
}
