use super::{ReadyHook, ReadyPoints};
use burn::backend::{Autodiff, Flex};
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::{Tensor, TensorData};
use std::sync::{Arc, Mutex};

type B = Autodiff<Flex>;

/// Records, at each point, the gradient it takes of the parameter that point completes.
struct Take {
    params: Vec<Tensor<B, 1>>,
    seen: Mutex<Vec<(usize, Vec<f32>)>>,
}

impl ReadyHook<B> for Take {
    fn ready(&self, point: usize, grads: &mut <B as AutodiffBackend>::Gradients) {
        let g = self.params[point]
            .grad_remove(grads)
            .map(|g| g.into_data().to_vec::<f32>().unwrap_or_default())
            .unwrap_or_default();
        if let Ok(mut s) = self.seen.lock() {
            s.push((point, g));
        }
    }
}

fn param(v: [f32; 2]) -> Tensor<B, 1> {
    Tensor::<B, 1>::from_data(TensorData::from(v), &Default::default()).require_grad()
}

#[test]
fn points_run_after_their_blocks_and_hand_over_complete_gradients() {
    let (w0, w1) = (param([2.0, 3.0]), param([5.0, 7.0]));
    let take = Arc::new(Take {
        params: vec![w0.clone(), w1.clone()],
        seen: Mutex::new(Vec::new()),
    });
    let points = ReadyPoints::new::<B>(take.clone());
    let x = param([1.0, 1.0]);
    // Two blocks, y = ((x · w0) · w1)², w1 read twice inside its block (its gradient has two parts).
    let h = points.mark(x.clone(), 0) * w0.clone();
    let h1 = points.mark(h, 1);
    let y = (h1.clone() * w1.clone()) * (h1 * w1.clone());
    let mut grads = y.sum().backward();
    let seen = take.seen.lock().map(|s| s.clone()).unwrap_or_default();
    // d/dw1 (x w0 w1)² = 2 (x w0)² w1; d/dw0 = 2 x² w0 w1².
    assert_eq!(
        seen,
        vec![(1, vec![40.0, 126.0]), (0, vec![100.0, 294.0])],
        "block 1's point runs first, each with its block's whole gradient"
    );
    // The marks pass the gradient through unchanged: d/dx = 2 x w0² w1².
    let gx = x
        .grad_remove(&mut grads)
        .map(|g| g.into_data().to_vec::<f32>().unwrap_or_default());
    assert_eq!(gx, Some(vec![200.0, 882.0]));
    // What the hook took is no longer in the container.
    assert!(w0.grad_remove(&mut grads).is_none() && w1.grad_remove(&mut grads).is_none());
}

#[test]
fn a_hook_made_for_another_backend_leaves_tensors_unmarked() {
    struct Never;
    impl ReadyHook<Autodiff<Flex, burn::backend::autodiff::checkpoint::strategy::BalancedCheckpointing>>
        for Never
    {
        fn ready(&self, _: usize, _: &mut burn::backend::autodiff::grads::Gradients) {
            panic!("called for another backend");
        }
    }
    let points = ReadyPoints::new(Arc::new(Never) as Arc<dyn ReadyHook<_>>);
    let w = param([2.0, 3.0]);
    let y = points.mark(w.clone(), 0) * w.clone();
    let mut grads = y.sum().backward();
    let g = w
        .grad_remove(&mut grads)
        .map(|g| g.into_data().to_vec::<f32>().unwrap_or_default());
    assert_eq!(g, Some(vec![4.0, 6.0]));
}
