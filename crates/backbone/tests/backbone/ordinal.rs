//! `backbone.ordinal_init`: the ordered value bins' embedding and head rows start as a sinusoid.

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
fn value_bins_start_as_a_sinusoid_and_only_they_do() {
    // Tests run in parallel on one seeded generator, so two builds do not draw the same numbers: each
    // model is checked on its own (that the other rows keep their draws is the unit tests' matter).
    let build = |on: bool| {
        let cfg = BackboneConfig {
            ordinal_init: on,
            ..config()
        };
        params(&Backbone::<F>::new(&cfg, &spec(), &Default::default()).unwrap())
    };
    let (e, d) = (config().embed(), config().d_model);
    let sqrt2 = std::f32::consts::SQRT_2;
    let head_scale = (2.0 / (3.0 * d as f32)).sqrt();
    // (tables of the ego and agent segments, heads of the ego segment, heads of the agent segment) whose
    // leading value bins hold the sinusoid; a table's or head's later rows are random draws, not more
    // sinusoid rows.
    let count = |ps: &[(Vec<usize>, Vec<f32>)]| {
        let mut n = (0, 0, 0);
        for (dims, v) in ps {
            match dims[..] {
                [18, w] if w == e && leading_rows(v, e, 16, sqrt2) => n.0 += 1,
                [12, w] if w == e && leading_rows(v, e, 8, sqrt2) => {
                    assert!(
                        !leading_rows(v, e, 9, sqrt2),
                        "agent table row 8 is not a value bin"
                    );
                    n.0 += 1
                }
                [r, 16] if r == d && leading_cols(v, 16, 16, head_scale) => n.1 += 1,
                [r, 10] if r == d && leading_cols(v, 10, 8, head_scale) => {
                    assert!(
                        !leading_cols(v, 10, 9, head_scale),
                        "agent head column 8 is not a value bin"
                    );
                    n.2 += 1
                }
                _ => {}
            }
        }
        n
    };
    // Two tables; TAR, OAR and ego-module heads for the ego, TAR and OAR heads for the agents.
    assert_eq!(count(&build(true)), (2, 3, 2));
    assert_eq!(count(&build(false)), (0, 0, 0));
}

#[test]
fn a_spec_with_more_value_bins_than_ids_is_refused() {
    let mut bad = spec();
    bad.segments[2].ordinal = 11;
    let err = Backbone::<F>::new(&config(), &bad, &Default::default()).unwrap_err();
    assert!(err.to_string().contains("agent"), "{err}");
}
