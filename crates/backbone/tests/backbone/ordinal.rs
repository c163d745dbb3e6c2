//! `backbone.ordinal_init`: the ordered value bins' embedding and head rows start as a sinusoid, and
//! nothing else changes.

use super::*;
use burn::module::{Module, ModuleVisitor, Param};
use umgen_backbone::ordinal::sinusoid;

/// Every parameter of `m` as `(dims, values)`, in visiting order.
fn params(m: &Backbone<F>) -> Vec<(Vec<usize>, Vec<f32>)> {
    struct Collect(Vec<(Vec<usize>, Vec<f32>)>);
    impl ModuleVisitor<F> for Collect {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<F, D>>) {
            let t = param.val();
            self.0
                .push((t.dims().to_vec(), t.into_data().to_vec::<f32>().unwrap()));
        }
    }
    let mut c = Collect(Vec::new());
    m.visit(&mut c);
    c.0
}

fn close(a: f32, b: f32) -> bool {
    (a - b).abs() < 1e-5
}

/// Whether the first `k` rows of a row-major `[rows, w]` matrix are `scale` × `sinusoid(k, w)`.
fn leading_rows(v: &[f32], w: usize, k: usize, scale: f32) -> bool {
    sinusoid(k, w).iter().zip(v).all(|(s, x)| close(s * scale, *x))
}

/// Whether the first `k` columns of a row-major `[d, cols]` matrix are `scale` × `sinusoid(k, d)`ᵀ.
fn leading_cols(v: &[f32], cols: usize, k: usize, scale: f32) -> bool {
    let d = v.len() / cols;
    let s = sinusoid(k, d);
    (0..d).all(|r| (0..k).all(|c| close(s[c * d + r] * scale, v[r * cols + c])))
}

#[test]
fn value_bins_start_as_a_sinusoid_and_nothing_else_moves() {
    let build = |on: bool| {
        F::seed(&Default::default(), 3);
        let cfg = BackboneConfig {
            ordinal_init: on,
            action: Some("ego".into()),
            ..config()
        };
        params(&Backbone::new(&cfg, &spec(), &Default::default()).unwrap())
    };
    let (on, off) = (build(true), build(false));
    assert_eq!(on.len(), off.len());
    let (e, d) = (config().embed(), config().d_model);
    let head_scale = (2.0 / (3.0 * d as f32)).sqrt();
    let (mut tables, mut heads) = (0, 0);
    for ((dims, a), (_, b)) in on.iter().zip(&off) {
        if a == b {
            continue;
        }
        // Tables of the ego (18 × E, 16 bins) and agent (12 × E, 8 bins) segments; their other rows kept.
        if let [rows @ (18 | 12), w] = dims[..]
            && w == e
        {
            let k = if rows == 18 { 16 } else { 8 };
            assert!(leading_rows(a, e, k, std::f32::consts::SQRT_2), "table {dims:?}");
            assert_eq!(a[k * e..], b[k * e..], "table {dims:?}: rows past the bins");
            tables += 1;
        // Heads [D, vocab] of the ego (16 bins of 16 ids) and agent (8 of 10) segments.
        } else if let [rows, cols @ (16 | 10)] = dims[..]
            && rows == d
        {
            let k = if cols == 16 { 16 } else { 8 };
            assert!(leading_cols(a, cols, k, head_scale), "head {dims:?}");
            for r in 0..d {
                assert_eq!(a[r * cols + k..(r + 1) * cols], b[r * cols + k..(r + 1) * cols]);
            }
            heads += 1;
        } else {
            panic!("parameter {dims:?} differs, but it holds no value bins");
        }
    }
    // Two tables; TAR and OAR heads of both segments, and the ego module's head.
    assert_eq!((tables, heads), (2, 5));
    assert!(
        off.iter()
            .all(|(dims, v)| !(dims[..] == [18, e] && leading_rows(v, e, 16, std::f32::consts::SQRT_2)))
    );
}

#[test]
fn a_spec_with_more_value_bins_than_ids_is_refused() {
    let mut bad = spec();
    bad.segments[2].ordinal = 11;
    let err = Backbone::<F>::new(&config(), &bad, &Default::default()).unwrap_err();
    assert!(err.to_string().contains("agent"), "{err}");
}
