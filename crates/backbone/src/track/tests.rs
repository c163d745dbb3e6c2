//! The moved slots against host computations and hand-worked cases.

use super::*;
use burn::tensor::TensorData;

type F = burn::backend::Flex;

fn spec() -> TrackSpec {
    TrackSpec {
        segment: 0,
        slot: 6,
        values: 8,
        fields: [
            (0, (-4.0, 4.0, 8)),
            (1, (-4.0, 4.0, 8)),
            (2, (-2.0, 2.0, 8)),
            (3, (-2.0, 2.0, 8)),
            (4, (-PI, PI, 8)),
        ],
        step_s: 0.5,
        pad: Some(9),
        accel: false,
        follow: None,
        stops: None,
    }
}

/// The moved slot on the host: the object's place after `step_s` in the plane of the current frame,
/// then seen from the next ego pose `(dx, dy, dθ)` as complex numbers (`(p − d)·e^{−iθ}`).
fn host(slot: &[i64], before: Option<(&[i64], f64)>, act: [f64; 3], k: &TrackSpec) -> (Vec<i64>, bool) {
    if slot[0] >= i64::from(k.values) {
        return (slot.to_vec(), false);
    }
    let value = |s: &[i64], j: usize| {
        let (i, (lo, hi, n)) = k.fields[j];
        lo + (s[i] as f64 + 0.5) * (hi - lo) / f64::from(n)
    };
    let value = |j: usize| value(slot, j);
    let (p, v) = ((value(0), value(1)), (value(2), value(3)));
    // e^{−iθ} as (cos, sin) of −θ, and complex multiplication by it.
    let turn = |theta: f64, (a, b): (f64, f64)| {
        let (c, s) = (theta.cos(), -theta.sin());
        (a * c - b * s, a * s + b * c)
    };
    // Constant acceleration: the change since the previous frame's velocity (turned into this frame);
    // none after an empty slot or where it would reverse the velocity.
    let dv = match before {
        Some((prev, theta)) if prev[0] < i64::from(k.values) => {
            let u = turn(theta, (value_of(prev, 2, k), value_of(prev, 3, k)));
            let d = (v.0 - u.0, v.1 - u.1);
            if (v.0 + d.0) * v.0 + (v.1 + d.1) * v.1 >= 0.0 {
                d
            } else {
                (0.0, 0.0)
            }
        }
        _ => (0.0, 0.0),
    };
    let step = (v.0 + 0.5 * dv.0, v.1 + 0.5 * dv.1);
    let q = turn(
        act[2],
        (p.0 + step.0 * k.step_s - act[0], p.1 + step.1 * k.step_s - act[1]),
    );
    let w = turn(act[2], (v.0 + dv.0, v.1 + dv.1));
    let h = (value(4) - act[2] + PI).rem_euclid(2.0 * PI) - PI;
    let mut out = slot.to_vec();
    let mut near_edge = false;
    for ((i, (lo, hi, n)), x) in k.fields.iter().zip([q.0, q.1, w.0, w.1, h]) {
        let f = (x - lo) / ((hi - lo) / f64::from(*n));
        near_edge |= (f - f.round()).abs() < 1e-4;
        out[*i] = (f.floor() as i64).clamp(0, i64::from(*n) - 1);
    }
    let inside = |x: f64, j: usize| (k.fields[j].1.0..k.fields[j].1.1).contains(&x);
    if let (Some(pad), false) = (k.pad, inside(q.0, 0) && inside(q.1, 1)) {
        out = vec![i64::from(pad); slot.len()];
    }
    (out, near_edge)
}

fn value_of(s: &[i64], j: usize, k: &TrackSpec) -> f64 {
    let (i, (lo, hi, n)) = k.fields[j];
    lo + (s[i] as f64 + 0.5) * (hi - lo) / f64::from(n)
}

#[test]
fn slots_move_as_a_host_computation_says() {
    let (b, t, s) = (2, 3, 5);
    let mut seed = 7u64;
    let mut draw = |n: u64| {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((seed >> 33) % n) as i64
    };
    // Values 0..8, category 8 in the last token; slot 2 of each frame empty (pad 9), and a few
    // others, so that some slots are new in their frame.
    let empty = |i: usize| i % s == 2 || i % 7 == 3;
    let ids: Vec<i64> = (0..b * t * s)
        .flat_map(|i| {
            (0..6)
                .map(|j| match (empty(i), j) {
                    (true, _) => 9,
                    (false, 5) => 8,
                    _ => draw(8),
                })
                .collect::<Vec<_>>()
        })
        .collect();
    let acts: Vec<f64> = (0..b * t)
        .flat_map(|i| {
            [
                0.9 + 0.37 * i as f64,
                -0.21 + 0.05 * i as f64,
                0.13 - 0.2 * i as f64,
            ]
        })
        .collect();
    let occupied = (0..b * t * s).filter(|&i| !empty(i)).count();
    for accel in [false, true] {
        let k = TrackSpec { accel, ..spec() };
        let dev = Default::default();
        let got = moved::<F>(
            Tensor::from_data(TensorData::new(ids.clone(), [b, t, s * k.slot]), &dev),
            None,
            Tensor::from_data(
                TensorData::new(acts.iter().map(|&a| a as f32).collect::<Vec<_>>(), [b, t, 3]),
                &dev,
            ),
            &k,
        );
        let got: Vec<i64> = got.into_data().iter::<i64>().collect();
        let (mut changed, mut left) = (0, 0);
        for (f, act) in acts.chunks(3).enumerate() {
            for slot in 0..s {
                let at = (f * s + slot) * k.slot;
                // The same slot one frame earlier in the window, and the ego's turn between them.
                let before = (accel && f % t > 0).then(|| {
                    let p = at - s * k.slot;
                    (&ids[p..p + k.slot], acts[3 * (f - 1) + 2])
                });
                let slot_ids = &ids[at..at + k.slot];
                let (want, near_edge) = host(slot_ids, before, [act[0], act[1], act[2]], &k);
                let have = &got[at..at + k.slot];
                if !near_edge {
                    assert_eq!(have, want.as_slice(), "accel {accel}, frame {f}, slot {slot}");
                }
                if empty(f * s + slot) {
                    continue;
                }
                if have.iter().all(|&id| id == 9) {
                    left += 1;
                } else {
                    assert_eq!(have[5], ids[at + 5], "the category stays");
                }
                changed += usize::from(have != slot_ids);
            }
        }
        assert!(changed + 4 >= occupied, "{changed} of {occupied} slots moved");
        // Both cases occur: slots that leave the ±4 m window (empty) and slots that stay.
        assert!(
            left >= 3 && left + 3 <= occupied,
            "{left} of {occupied} slots left"
        );
    }
}

#[test]
fn constant_acceleration_keeps_the_change_and_stops_rather_than_reverses() {
    // Two frames of one slot (x 0.5 m, y 1.5 m, vy 0.25 m/s), no ego motion. vx 0.75 m/s after
    // −1.75: the change (2.5 m/s) kept puts x at 0.5 + 0.5 · (0.75 + 1.25) = 1.5 m (bin 5; 0.875 m, bin
    // 4, at constant velocity) and vx at 3.25 m/s (past the range: bin 7). Braking from 1.75 to 0.25
    // m/s would reverse it (−1.25): constant velocity instead.
    let dev = Default::default();
    let run = |vx: [i64; 2], accel: bool| {
        let ids = vec![4i64, 5, vx[0], 4, 4, 8, 4, 5, vx[1], 4, 4, 8];
        moved::<F>(
            Tensor::from_data(TensorData::new(ids, [1, 2, 6]), &dev),
            None,
            Tensor::from_data(TensorData::new(vec![0.0f32; 6], [1, 2, 3]), &dev),
            &TrackSpec { accel, ..spec() },
        )
        .into_data()
        .iter::<i64>()
        .collect::<Vec<_>>()
    };
    // The window's first frame has no past: constant velocity (x −0.375 m, bin 3).
    assert_eq!(run([0, 5], true), vec![3, 5, 0, 4, 4, 8, 5, 5, 7, 4, 4, 8]);
    assert_eq!(run([0, 5], false)[6..], [4, 5, 5, 4, 4, 8]);
    assert_eq!(run([7, 4], true)[6..], [4, 5, 4, 4, 4, 8]);
}

#[test]
fn a_standing_ego_and_object_stay_in_their_bins() {
    // No ego motion, no velocity (bins 3 and 4 of ±2 m/s straddle 0: centre ±0.25 m/s moves 0.125 m,
    // inside the 1 m bin from its centre), heading kept: the same ids.
    let k = spec();
    let slot = [2i64, 5, 4, 3, 6, 8];
    let dev = Default::default();
    let got = moved::<F>(
        Tensor::from_data(TensorData::new(slot.to_vec(), [1, 1, 6]), &dev),
        None,
        Tensor::from_data(TensorData::new(vec![0.0f32; 3], [1, 1, 3]), &dev),
        &k,
    );
    assert_eq!(got.into_data().iter::<i64>().collect::<Vec<_>>(), slot.to_vec());
}

#[test]
fn a_slot_moved_out_of_the_window_empties_where_there_is_a_pad() {
    // x at bin 7 (3.5 m) with vx at bin 7 (1.75 m/s): 0.875 m further is past the +4 m edge.
    let slot = [7i64, 5, 7, 4, 6, 8];
    let dev = Default::default();
    let run = |k: &TrackSpec| {
        moved::<F>(
            Tensor::from_data(TensorData::new(slot.to_vec(), [1, 1, 6]), &dev),
            None,
            Tensor::from_data(TensorData::new(vec![0.0f32; 3], [1, 1, 3]), &dev),
            k,
        )
        .into_data()
        .iter::<i64>()
        .collect::<Vec<_>>()
    };
    assert_eq!(
        run(&spec()),
        vec![9; 6],
        "the data drops agents that leave the window"
    );
    let clamped = run(&TrackSpec { pad: None, ..spec() });
    assert_eq!(clamped, vec![7, 5, 7, 4, 6, 8], "without a pad: the end bin");
}

#[test]
fn a_slot_closing_on_a_standing_one_ahead_in_its_lane_brakes_to_meet_it() {
    // Bins of 0.125 m, 0.039 m/s and 0.35°; no ego motion. Slot 0 drives along +x at 10 m/s with
    // slot 1 standing 20 m ahead, 0.3 m aside. Slot 2 drives at 10 m/s 65 m behind slot 1 (0.87 m/s²
    // would do: under the onset) and 45 m behind slot 0, as fast as it. Slot 3 drives in the next lane,
    // slot 5 towards slot 0 from ahead, slot 4 is empty.
    let lo_v = -20.0;
    let k = TrackSpec {
        slot: 6,
        values: 1024,
        fields: [
            (0, (-64.0, 64.0, 1024)),
            (1, (-64.0, 64.0, 1024)),
            (2, (lo_v, 20.0, 1024)),
            (3, (lo_v, 20.0, 1024)),
            (4, (-PI, PI, 1024)),
        ],
        pad: Some(1027),
        follow: Some(FollowSpec::default()),
        ..spec()
    };
    let bin = |j: usize, v: f64| {
        let (lo, hi, n) = k.fields[j].1;
        ((v - lo) / ((hi - lo) / f64::from(n))).floor() as i64
    };
    let car = |x: f64, y: f64, v: f64, h: f64| {
        [
            bin(0, x),
            bin(1, y),
            bin(2, v * h.cos()),
            bin(3, v * h.sin()),
            bin(4, h),
            1024,
        ]
    };
    let frame: Vec<i64> = [
        car(0.06, 0.06, 10.0, 0.0),
        car(20.0, 0.3, 0.0, 0.0),
        car(-45.0, 0.0, 10.0, 0.0),
        car(0.0, 10.0, 10.0, 0.0),
        [1027; 6],
        car(10.0, -0.2, 10.0, PI - 0.01),
    ]
    .concat();
    let dev = Default::default();
    let run = |k: &TrackSpec| {
        moved::<F>(
            Tensor::from_data(TensorData::new(frame.clone(), [1, 1, 36]), &dev),
            None,
            Tensor::from_data(TensorData::new(vec![0.0f32; 3], [1, 1, 3]), &dev),
            k,
        )
        .into_data()
        .iter::<i64>()
        .collect::<Vec<_>>()
    };
    let (braked, kept) = (
        run(&k),
        run(&TrackSpec {
            follow: None,
            ..k.clone()
        }),
    );
    assert_eq!(
        braked[6..],
        kept[6..],
        "only slot 0 has a slower leader near enough"
    );
    // Slot 0 from its bins' centres: (u0 − u1)² / (2 (along − 7.5 m)) ≈ 4 m/s², 2 m/s less over the
    // step, half of that on the way.
    let at = |s: usize, j: usize| value_of(&frame[6 * s..6 * s + 6], j, &k);
    let (u0, u1) = (at(0, 2), at(1, 2));
    let need = (u0 - u1).powi(2) / (2.0 * (at(1, 0) - at(0, 0) - 7.5));
    assert!((need - 4.0).abs() < 0.1, "{need}");
    let v = u0 - 0.5 * need;
    assert_eq!(braked[0], bin(0, at(0, 0) + 0.5 * (u0 + v) / 2.0));
    assert_eq!(braked[2], bin(2, v));
    assert!(kept[2] - braked[2] >= 50, "{} against {}", braked[2], kept[2]);
    // A leader at 9.9 m/s: closing at 0.1 m/s asks for next to nothing, under the onset.
    let mut slow = frame.clone();
    slow[8] = bin(2, 9.9);
    let got = moved::<F>(
        Tensor::from_data(TensorData::new(slow, [1, 1, 36]), &dev),
        None,
        Tensor::from_data(TensorData::new(vec![0.0f32; 3], [1, 1, 3]), &dev),
        &k,
    );
    assert_eq!(got.into_data().iter::<i64>().next(), Some(kept[0]));
}
