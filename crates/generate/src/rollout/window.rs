//! The window pass of a new frame: the history window embedded once, the ego module's action and the TAR
//! prior, a group of scenes at a time.

use super::{Generator, host_rows};
use burn::tensor::backend::Backend;
use burn::tensor::{Int, Tensor, TensorData};
use umgen_backbone::{Kernels, Slot};

impl<B: Backend> Generator<'_, B> {
    /// The next frame's action (`forced`, or drawn from the ego module) and TAR prior `[m, N, d]`, from the
    /// windows of `history`, embedded once for both, a group of scenes at a time (`pass_frames`). Scenes
    /// are taken in order, so the action draws come in the same order whatever the group size.
    pub(super) fn window_pass(
        &mut self,
        history: &[Vec<Vec<u32>>],
        forced: Option<&Vec<Vec<u32>>>,
        dev: &B::Device,
    ) -> (Option<Vec<Vec<u32>>>, Tensor<B, 3>) {
        let (m, n) = (history.len(), self.model.spec().n);
        let t = history[0].len();
        if t == 0 {
            // An initial scene: no history, no TAR (as in the paper).
            let h = Tensor::zeros([m, n, self.model.embed_width()], dev);
            return (forced.cloned(), h);
        }
        let per = (self.pass_frames / t.min(self.window)).max(1);
        let (mut drawn, mut priors) = (Vec::new(), Vec::new());
        for start in (0..m).step_by(per) {
            let part = &history[start..(start + per).min(m)];
            let tokens = self.window_tensor(part, dev);
            let e = self.model.embed.forward(tokens.clone(), &Kernels::DEFAULT);
            let action = match forced {
                Some(a) => Some(a[start..start + part.len()].to_vec()),
                None => self.predict_action(e.clone()),
            };
            priors.push(self.prior(tokens, e, action.as_ref(), dev));
            if forced.is_none() {
                drawn.extend(action.into_iter().flatten());
            }
        }
        let action = forced.cloned().or((!drawn.is_empty()).then_some(drawn));
        (action, Tensor::cat(priors, 0))
    }

    /// The last `window` frames as a tensor `[m, w, N]`.
    fn window_tensor(&self, history: &[Vec<Vec<u32>>], dev: &B::Device) -> Tensor<B, 3, Int> {
        let t = history[0].len();
        let w = t.min(self.window);
        let n = self.model.spec().n;
        let ids: Vec<i64> = history
            .iter()
            .flat_map(|h| h[t - w..].iter().flatten().map(|&x| i64::from(x)))
            .collect();
        Tensor::from_data(TensorData::new(ids, [history.len(), w, n]), dev)
    }

    /// The ego module's action for the frame after the embedded window `e` `[m, w, N, d]`.
    fn predict_action(&mut self, e: Tensor<B, 4>) -> Option<Vec<Vec<u32>>> {
        let a = self.model.spec().action.as_ref()?;
        let logits = self.model.ego_logits(e, true)?;
        let [m, _, q, v] = logits.dims();
        let rows = host_rows(logits.reshape([m * q, v]));
        let s = self.sampling[a.segment];
        Some(
            rows.chunks(q)
                .map(|r| r.iter().map(|l| s.draw(l, &mut self.rng)).collect())
                .collect(),
        )
    }

    /// The TAR prior `[m, N, d]` of the frame after the window `tokens` `[m, w, N]` (embedded: `e`).
    fn prior(
        &self,
        tokens: Tensor<B, 3, Int>,
        e: Tensor<B, 4>,
        action: Option<&Vec<Vec<u32>>>,
        dev: &B::Device,
    ) -> Tensor<B, 3> {
        let spec = self.model.spec();
        let [m, w, n] = tokens.dims();
        let d = self.model.embed_width();
        // The new frame as far as it is known: its boundary tokens and action.
        let mut known = vec![0i64; m * n];
        for (b, row) in known.chunks_mut(n).enumerate() {
            for (p, slot) in self.slots.iter().enumerate() {
                row[p] = match *slot {
                    Slot::Start(s) => spec.segments[s].vocab as i64,
                    Slot::End(s) => spec.segments[s].vocab as i64 + 1,
                    Slot::Content(s, i) => match (&spec.action, action) {
                        (Some(a), Some(act)) if a.segment == s && i < act[b].len() => i64::from(act[b][i]),
                        _ => 0,
                    },
                };
            }
        }
        let new = Tensor::<B, 3, Int>::from_data(TensorData::new(known, [m, 1, n]), dev);
        // Frames embed independently: only the new one needs embedding.
        let e_new = self.model.embed.forward(new.clone(), &Kernels::DEFAULT);
        let e_next = if w > 1 {
            Tensor::cat(vec![e.clone().narrow(1, 1, w - 1), e_new], 1)
        } else {
            e_new
        };
        let next_action = spec.action.as_ref().filter(|_| action.is_some()).map(|a| {
            let s = &spec.segments[a.segment];
            Tensor::cat(vec![tokens.clone(), new], 1)
                .narrow(1, 1, w)
                .narrow(2, s.offset, s.tokens)
        });
        let h = self.model.tar(tokens, e, e_next, next_action);
        h.narrow(1, w - 1, 1).reshape([m, n, d])
    }
}
