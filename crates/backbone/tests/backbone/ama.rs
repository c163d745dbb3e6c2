//! AMA against hand-computed moves.

use super::F;
use burn::tensor::{Tensor, TensorData};
use umgen_backbone::align;

/// A 4×4 grid with feature = 1 at (row, col), 0 elsewhere, one channel.
fn one_hot(r: usize, c: usize) -> Tensor<F, 3> {
    let mut v = vec![0.0f32; 16];
    v[r * 4 + c] = 1.0;
    Tensor::from_data(TensorData::new(v, [1, 16, 1]), &Default::default())
}

fn moved(f: Tensor<F, 3>, dx: f32, dy: f32, th: f32) -> Vec<f32> {
    let a = Tensor::<F, 2>::from_data(TensorData::new(vec![dx, dy, th], [1, 3]), &Default::default());
    align(f, a, 4, 4, 2.0).into_data().iter::<f32>().collect()
}

fn at(v: &[f32], r: usize, c: usize) -> f32 {
    v[r * 4 + c]
}

#[test]
fn zero_motion_is_the_identity() {
    let f = Tensor::<F, 3>::from_data(
        TensorData::new((0..32).map(|i| i as f32 * 0.1).collect::<Vec<_>>(), [1, 16, 2]),
        &Default::default(),
    );
    let a = Tensor::<F, 2>::zeros([1, 3], &Default::default());
    let out: Vec<f32> = align(f.clone(), a, 4, 4, 2.0).into_data().iter::<f32>().collect();
    let want: Vec<f32> = f.into_data().iter::<f32>().collect();
    for (o, w) in out.iter().zip(want) {
        assert!((o - w).abs() < 1e-5);
    }
}

#[test]
fn driving_one_cell_forward_shifts_the_map_back_one_row() {
    // Cells are 2 m: after 2 m forward, what was at row 1 is at row 2; the front row empties.
    let out = moved(one_hot(1, 2), 2.0, 0.0, 0.0);
    assert!((at(&out, 2, 2) - 1.0).abs() < 1e-5, "{out:?}");
    assert!(out.iter().enumerate().all(|(i, v)| i == 10 || v.abs() < 1e-5));
    // 2 m to the left: columns shift right.
    let out = moved(one_hot(1, 1), 0.0, 2.0, 0.0);
    assert!((at(&out, 1, 2) - 1.0).abs() < 1e-5, "{out:?}");
    // Half a cell forward: split between two rows.
    let out = moved(one_hot(1, 2), 1.0, 0.0, 0.0);
    assert!(
        (at(&out, 1, 2) - 0.5).abs() < 1e-5 && (at(&out, 2, 2) - 0.5).abs() < 1e-5,
        "{out:?}"
    );
}

#[test]
fn turning_left_brings_the_left_ahead() {
    // A feature 3 m left of the ego (row 1.5 = the centre line, column 0.5) after a 90° left turn lies
    // 3 m ahead: column 1.5, row 0.5. On a 4×4 grid the centre is between cells, so use the 2×2 block.
    let mut v = vec![0.0f32; 16];
    for r in 1..3 {
        v[r * 4] = 1.0;
    }
    let f = Tensor::<F, 3>::from_data(TensorData::new(v, [1, 16, 1]), &Default::default());
    let out = moved(f, 0.0, 0.0, std::f32::consts::FRAC_PI_2);
    assert!(
        (at(&out, 0, 1) - 1.0).abs() < 1e-4 && (at(&out, 0, 2) - 1.0).abs() < 1e-4,
        "{out:?}"
    );
    assert!(
        at(&out, 3, 1).abs() < 1e-4 && at(&out, 1, 0).abs() < 1e-4,
        "{out:?}"
    );
}
