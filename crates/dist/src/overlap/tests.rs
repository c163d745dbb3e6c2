use super::Overlap;
use crate::fake::{Fake, Starts};
use burn::backend::{Autodiff, Flex};
use burn::module::{Module, Param, ParamId};
use burn::optim::{GradientsAccumulator, GradientsParams};
use burn::tensor::backend::Backend;
use burn::tensor::{Tensor, TensorData};
use std::sync::Arc;
use umgen_ops::ready::ReadyPoints;

type AD = Autodiff<Flex>;
type I = Flex;

/// (burn's derive recognises the backend parameter by its name, `B`.)
#[derive(Module, Debug)]
struct Net<B: Backend> {
    a: Param<Tensor<B, 1>>,
    b: Param<Tensor<B, 2>>,
    c: Param<Tensor<B, 1>>,
    unused: Param<Tensor<B, 1>>,
}

fn net() -> Net<AD> {
    let d = Default::default();
    let t1 = |v: &[f32]| {
        Param::from_tensor(Tensor::<AD, 1>::from_data(
            TensorData::new(v.to_vec(), [v.len()]),
            &d,
        ))
    };
    Net {
        a: t1(&[0.5, -1.0, 2.0]),
        b: Param::from_tensor(Tensor::from_data(
            TensorData::new(vec![1.0f32, 2.0, -0.5, 0.25, 3.0, -1.5], [3, 2]),
            &d,
        )),
        c: t1(&[0.1, 0.2]),
        unused: t1(&[9.0]),
    }
}

/// Block 0 reads `a`, block 1 reads `b`; `c` is read after both (no point).
fn loss(n: &Net<AD>, x: [f32; 3], points: Option<&ReadyPoints>) -> Tensor<AD, 1> {
    let mark = |t: Tensor<AD, 1>, p| match points {
        Some(r) => r.mark(t, p),
        None => t,
    };
    // Tracked, as a model's first block input is (embeddings): a point on an untracked tensor never runs.
    let x = Tensor::<AD, 1>::from_floats(x, &Default::default()).require_grad();
    let h = mark(x, 0) * n.a.val();
    let h = mark(h, 1).reshape([1, 3]).matmul(n.b.val()).reshape([2]);
    (h.clone() * h * n.c.val()).sum()
}

fn groups(n: &Net<AD>) -> Vec<Vec<ParamId>> {
    vec![vec![n.a.id], vec![n.b.id]]
}

fn values(g: &mut GradientsParams, n: &Net<AD>) -> Vec<Vec<f32>> {
    let v = |t: Option<Tensor<I, 1>>| {
        t.map(|t| t.into_data().to_vec::<f32>().unwrap_or_default())
            .unwrap_or_default()
    };
    vec![
        v(g.remove::<I, 1>(n.a.id)),
        v(g.remove::<I, 2>(n.b.id).map(|t| t.flatten(0, 1))),
        v(g.remove::<I, 1>(n.c.id)),
        v(g.remove::<I, 1>(n.unused.id)),
    ]
}

/// Two micro-steps, plain: what the overlapped step must reproduce (plus one per element from the
/// recorder's "mean").
fn plain(n: &Net<AD>) -> Vec<Vec<f32>> {
    let mut acc = GradientsAccumulator::<Net<AD>>::new();
    for x in [[1.0, 2.0, 3.0], [-1.0, 0.5, 2.0]] {
        acc.accumulate::<AD>(
            n,
            GradientsParams::from_grads::<AD, _>(loss(n, x, None).backward(), n),
        );
    }
    let mut g = acc.grads();
    values(&mut g, n)
}

#[test]
fn buckets_close_at_points_in_backward_order_and_gradients_match_the_plain_step() {
    let n = net();
    let expected = plain(&n);
    let mut acc = GradientsAccumulator::<Net<AD>>::new();
    acc.accumulate::<AD>(
        &n,
        GradientsParams::from_grads::<AD, _>(loss(&n, [1.0, 2.0, 3.0], None).backward(), &n),
    );
    let mut group = Fake::default();
    // One float a bucket: each point closes its own.
    let step = Overlap::<AD>::new(&n, &groups(&n), acc.grads(), &group, 4);
    let grads = loss(&n, [-1.0, 0.5, 2.0], Some(&step.points())).backward();
    let mut out = step.finish(grads, &mut group).expect("finish");
    // Block 1 (b, 6 floats) first, then block 0 (a, 3), then what no point took, in module order.
    assert_eq!(group.calls, vec![6, 3, 2, 1]);
    let got = values(&mut out, &n);
    for (g, e) in got.iter().zip(&expected) {
        let e: Vec<f32> = if e.is_empty() { vec![0.0] } else { e.clone() };
        let e: Vec<f32> = e.iter().map(|x| x + 1.0).collect();
        assert_eq!(g.len(), e.len());
        for (a, b) in g.iter().zip(&e) {
            assert!(
                (a - b).abs() <= 1e-5 * b.abs().max(1.0),
                "{got:?} against {expected:?}"
            );
        }
    }
}

#[test]
fn one_large_bucket_holds_everything_in_one_collective() {
    let n = net();
    let mut group = Fake::default();
    let step = Overlap::<AD>::new(&n, &groups(&n), GradientsParams::new(), &group, 1 << 20);
    let grads = loss(&n, [1.0, 2.0, 3.0], Some(&step.points())).backward();
    step.finish(grads, &mut group).expect("finish");
    // The points' gradients (9) wait for more until the backward pass ends; the rest (3) is a bucket of
    // its own.
    assert_eq!(group.calls, vec![9, 3]);
}

#[test]
fn a_parameter_read_outside_its_block_is_named() {
    let n = net();
    let mut group = Fake::default();
    // `a` declared in block 1, but read before it (in block 0).
    let points = vec![vec![], vec![n.b.id, n.a.id]];
    let step = Overlap::<AD>::new(&n, &points, GradientsParams::new(), &group, 4);
    let grads = loss(&n, [1.0, 2.0, 3.0], Some(&step.points())).backward();
    let err = step
        .finish(grads, &mut group)
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default();
    assert!(
        err.contains(&n.a.id.to_string()) && err.contains("outside its block"),
        "{err}"
    );
}

#[test]
fn a_group_that_can_start_averages_starts_them_during_the_backward_pass() {
    let n = net();
    let starts = Arc::new(Starts::default());
    let mut group = Fake {
        starts: Some(starts.clone()),
        ..Fake::default()
    };
    let step = Overlap::<AD>::new(&n, &groups(&n), GradientsParams::new(), &group, 4);
    let grads = loss(&n, [1.0, 2.0, 3.0], Some(&step.points())).backward();
    *starts.returned.lock().expect("lock") = true;
    let mut out = step.finish(grads, &mut group).expect("finish");
    assert_eq!(
        *starts.log.lock().expect("lock"),
        vec![
            "start 6 during",
            "start 3 during",
            "start 2 after",
            "start 1 after",
            "settle 4"
        ]
    );
    // Every gradient came through a started average (+1).
    let expected = {
        let mut g = GradientsParams::from_grads::<AD, _>(loss(&n, [1.0, 2.0, 3.0], None).backward(), &n);
        values(&mut g, &n)
    };
    let got = values(&mut out, &n);
    assert_eq!(got[3], vec![1.0]);
    for (g, e) in got.iter().zip(&expected).take(3) {
        for (a, b) in g.iter().zip(e) {
            assert!((a - (b + 1.0)).abs() <= 1e-5 * b.abs().max(1.0));
        }
    }
}

#[test]
fn points_kept_past_the_step_do_not_stop_it() {
    let n = net();
    let mut group = Fake::default();
    let step = Overlap::<AD>::new(&n, &groups(&n), GradientsParams::new(), &group, 4);
    // The caller keeps the points (and so the hook) alive past `finish`.
    let points = step.points();
    let grads = loss(&n, [1.0, 2.0, 3.0], Some(&points)).backward();
    step.finish(grads, &mut group).expect("finish");
    assert_eq!(group.calls, vec![6, 3, 2, 1]);
    // A later backward pass through the same points finds nothing to do.
    let _ = loss(&n, [1.0, 2.0, 3.0], Some(&points)).backward();
    assert_eq!(group.calls.len(), 4);
}
