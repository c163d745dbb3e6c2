//! AdamW over all parameter tensors at once.
//!
//! burn's `OptimizerAdaptor<AdamW>` steps one parameter tensor at a time, a chain of about ten tensor
//! operations each: `small` has 331 parameter tensors, and on CUDA the chain's host work took 17–22 ms a
//! step against PyTorch's fused AdamW's 0.7 ms (docs/decisions/007-memory-bound-training-kernels.md). [`FusedAdamW`] gathers every
//! parameter, gradient and moment of a step into [`AdamWSlot`]s and hands them to a backend's
//! multi-tensor [`AdamWKernel`] (umgen's CUDA kernel updates them all in a few launches), and steps
//! tensor by tensor with burn's own `AdamW` where there is none, or where the kernel declines. It keeps
//! burn's record, so checkpoints written by either load into the other, and it takes the gradient
//! clipping's factor as a device tensor so that clipping costs no pass over the gradients of its own.

use crate::kernels::{AdamWSlot, AdamWStep, GradNorm, MultiTensor, norm_reference, typed1};
use crate::skip::{GradientPeak, guarded_scale, skip_mask, unless_skipped};
use burn::module::{AutodiffModule, ModuleMapper, ModuleVisitor, Param, ParamId};
use burn::optim::adaptor::{GradAdaptor, OptimizerAdaptor};
use burn::optim::record::AdaptorRecord;
use burn::optim::{
    AdamW, AdamWConfig, AdamWState, AdaptiveMomentumState, GradientsParams, LearningRate,
    MultiGradientsParams, Optimizer, SimpleOptimizer,
};
use burn::tensor::backend::{AutodiffBackend, Backend};
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Tensor, TensorPrimitive};
use std::collections::{HashMap, HashSet};
use std::marker::PhantomData;

/// AdamW's hyper-parameters: burn's `AdamWConfig` without AMSGrad, cautious weight decay or per-tensor
/// clipping (umgen clips by the global norm, [`FusedAdamW::step_clipped`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamWSettings {
    /// Decay of the first moment.
    pub beta_1: f32,
    /// Decay of the second moment.
    pub beta_2: f32,
    /// Added to √v̂.
    pub epsilon: f32,
    /// Decoupled weight decay (per unit of learning rate).
    pub weight_decay: f32,
}

impl AdamWSettings {
    /// burn's AdamW with these settings (the per-tensor path, and the reference the kernels match).
    fn burn(&self) -> AdamW {
        AdamWConfig::new()
            .with_beta_1(self.beta_1)
            .with_beta_2(self.beta_2)
            .with_epsilon(self.epsilon)
            .with_weight_decay(self.weight_decay)
            .build()
    }
}

/// What [`FusedAdamW::step_clipped`] did, on the device (nothing here makes the host wait).
#[derive(Debug)]
pub struct Stepped<M, B: Backend> {
    /// The module after the step (as it was, if the step was skipped).
    pub module: M,
    /// `[1]`: the gradients' global norm before clipping.
    pub norm: Tensor<B, 1>,
    /// `[1]`: 1 if the step was skipped (a non-finite norm or guard value), else 0.
    pub skipped: Tensor<B, 1>,
    /// `[K]`: the gradients' sums of squares by part ([`FusedAdamW::largest_gradient`] names the largest).
    pub parts: Tensor<B, 1>,
}

/// burn's AdamW record for a module `M`, which [`FusedAdamW`] keeps too.
pub type AdamWRecord<M, B> = <OptimizerAdaptor<AdamW, M, B> as Optimizer<M, B>>::Record;

/// A clipped step's gradient norm and whether it was skipped (`[1]`, 0 or 1).
struct Checked<B: Backend> {
    norm: GradNorm<B>,
    skipped: Tensor<B, 1>,
}

/// AdamW stepping every parameter tensor at once through an [`AdamWKernel`] when there is one.
#[derive(Clone)]
pub struct FusedAdamW<M: AutodiffModule<B>, B: AutodiffBackend> {
    settings: AdamWSettings,
    records: AdamWRecord<M, B>,
    kernels: Option<MultiTensor<B::InnerBackend>>,
    /// The module path of each parameter that had a gradient in the last step, in module order (the
    /// norm's: owned or not).
    names: Vec<String>,
    /// How many of the last step's [`Stepped::parts`] each of those gradients has.
    spans: Vec<usize>,
    /// The parameters this optimizer updates (all when `None`), [`FusedAdamW::set_owned`].
    owned: Option<HashSet<ParamId>>,
    module: PhantomData<M>,
}

impl<M: AutodiffModule<B>, B: AutodiffBackend> FusedAdamW<M, B> {
    /// An optimizer with `settings` and no state, stepping tensor by tensor until given a kernel.
    pub fn new(settings: AdamWSettings) -> Self {
        Self {
            settings,
            records: Default::default(),
            kernels: None,
            names: Vec::new(),
            spans: Vec::new(),
            owned: None,
            module: PhantomData,
        }
    }

    /// Updates only the parameters in `owned` from now on (all of them with `None`): optimizer-state
    /// sharding, where each rank updates its share and another copies the result to all. The other
    /// parameters' gradients still enter the global norm that clipping and the skip guard read (in module
    /// order, so the norm is the unsharded one), but their values stay as they are and they get no
    /// moments; moments already held for them are dropped, so that their memory is freed.
    pub fn set_owned(&mut self, owned: Option<HashSet<ParamId>>) {
        if let Some(keep) = &owned {
            self.records.retain(|id, _| keep.contains(id));
        }
        self.owned = owned;
    }

    /// Steps through `kernels` from now on (`None`: tensor by tensor, with burn's AdamW).
    pub fn with_kernels(mut self, kernels: Option<MultiTensor<B::InnerBackend>>) -> Self {
        self.set_kernels(kernels);
        self
    }

    /// [`Self::with_kernels`] on an optimizer in use: the moments stay, so steps may take turns between a
    /// backend's kernels and burn's AdamW (both read and write the same record).
    pub fn set_kernels(&mut self, kernels: Option<MultiTensor<B::InnerBackend>>) {
        self.kernels = kernels;
    }

    /// One AdamW step of `module` with `grads` scaled to a global norm of at most `max_norm` (not scaled
    /// when `max_norm <= 0`), as [`crate::clip_grad_norm`] scales them. The scaling happens as the step
    /// reads each gradient, so clipping costs no pass over the gradients of its own.
    ///
    /// The step is skipped, on the device, when the norm or any value of `guard` (e.g. the loss) is not
    /// finite: parameters and moments stay as they were (a skipped first step leaves zero moments), and
    /// only AdamW's step count, which sets its bias corrections, still counts it. The host learns of it
    /// when it reads [`Stepped::skipped`].
    pub fn step_clipped(
        &mut self,
        lr: LearningRate,
        module: M,
        grads: GradientsParams,
        max_norm: f64,
        guard: Option<Tensor<B::InnerBackend, 1>>,
    ) -> Stepped<M, B::InnerBackend> {
        let (module, norm) = self.step_adapted(lr, module, grads.into(), Some((max_norm, guard)));
        let zero = || Tensor::zeros([1], &Default::default());
        match norm {
            Some(Checked { norm, skipped }) => Stepped {
                module,
                norm: norm.norm,
                skipped,
                parts: norm.parts,
            },
            None => Stepped {
                module,
                norm: zero(),
                skipped: zero(),
                parts: zero(),
            },
        }
    }

    /// Which parameter's gradient stands out among `parts` (the sums of squares of a latest step's
    /// [`Stepped::parts`], read back): the first, in module order, whose norm is not finite, or else the
    /// largest. `None` when there were no gradients.
    pub fn largest_gradient(&self, parts: &[f32]) -> Option<GradientPeak> {
        let mut rest = parts;
        let sums: Vec<f64> = self
            .spans
            .iter()
            .take(self.names.len())
            .map(|&k| {
                let (mine, after) = rest.split_at(k.min(rest.len()));
                rest = after;
                mine.iter().map(|&sq| f64::from(sq)).sum()
            })
            .collect();
        let non_finite = sums.iter().filter(|s| !s.is_finite()).count();
        let i = match sums.iter().position(|s| !s.is_finite()) {
            Some(i) => i,
            None => sums.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1))?.0,
        };
        Some(GradientPeak {
            name: self.names.get(i)?.clone(),
            norm: sums[i].sqrt(),
            non_finite,
            params: sums.len(),
        })
    }

    /// The global norm of `grads` (`[1]`), through the norm kernel when there is one.
    fn norm(&self, grads: &[FloatTensor<B::InnerBackend>]) -> Option<GradNorm<B::InnerBackend>> {
        if grads.is_empty() {
            return None;
        }
        let by_kernel = self.kernels.as_ref().and_then(|k| (k.norm)(grads).ok());
        Some(by_kernel.unwrap_or_else(|| norm_reference::<B::InnerBackend>(grads)))
    }

    fn step_adapted(
        &mut self,
        lr: LearningRate,
        module: M,
        grads: GradAdaptor,
        clip: Option<(f64, Option<Tensor<B::InnerBackend, 1>>)>,
    ) -> (M, Option<Checked<B::InnerBackend>>) {
        let mut gather = Gather::<M, B> {
            grads,
            records: &mut self.records,
            owned: self.owned.as_ref(),
            ids: Vec::new(),
            slots: Vec::new(),
            all: Vec::new(),
            path: Vec::new(),
            names: (self.names.is_empty() && clip.is_some()).then(Vec::new),
        };
        module.visit(&mut gather);
        let Gather {
            ids,
            slots,
            all,
            names,
            ..
        } = gather;
        if let Some(names) = names {
            self.names = names;
        }
        let norm = clip.as_ref().and_then(|_| self.norm(&all));
        // The gradients of parameters another rank updates are needed no further.
        drop(all);
        let guarded = match (&norm, clip) {
            (Some(norm), Some((max_norm, guard))) => {
                self.spans.clone_from(&norm.spans);
                Some(guarded_scale(norm.norm.clone(), max_norm, guard))
            }
            _ => None,
        };
        let step = AdamWStep {
            settings: self.settings,
            lr,
            grad_scale: guarded.clone().map(|s| s.into_primitive().tensor()),
        };
        let stepped = match &self.kernels {
            Some(kernels) if !slots.is_empty() => (kernels.adamw)(slots, &step),
            _ => Err((slots, String::new())),
        };
        let outcomes = match stepped {
            Ok(outputs) => {
                let times = ids.iter().map(|(_, t)| *t);
                let done = outputs.into_iter().zip(times).map(|(o, t)| Outcome::Done(o, t));
                ids.iter().map(|(id, _)| *id).zip(done).collect()
            }
            Err((slots, _)) => {
                let pending = slots.into_iter().map(Outcome::Pending);
                ids.iter().map(|(id, _)| *id).zip(pending).collect()
            }
        };
        let module = module.map(&mut Apply::<M, B> {
            outcomes,
            step: &step,
            burn: self.settings.burn(),
            records: &mut self.records,
        });
        let skipped = guarded.map(|scale| scale.is_finite().bool_not().float());
        let checked = norm.zip(skipped).map(|(norm, skipped)| Checked { norm, skipped });
        (module, checked)
    }
}

impl<M: AutodiffModule<B>, B: AutodiffBackend> Optimizer<M, B> for FusedAdamW<M, B> {
    type Record = AdamWRecord<M, B>;

    fn step(&mut self, lr: LearningRate, module: M, grads: GradientsParams) -> M {
        self.step_adapted(lr, module, grads.into(), None).0
    }

    fn step_multi(&mut self, lr: LearningRate, module: M, grads: MultiGradientsParams) -> M {
        self.step_adapted(lr, module, grads.into(), None).0
    }

    fn to_record(&self) -> Self::Record {
        self.records.clone()
    }

    fn load_record(mut self, record: Self::Record) -> Self {
        self.records = record;
        self
    }
}

/// Collects the slot of every parameter that has a gradient (and is owned, when only some are), taking its
/// state out of the records.
struct Gather<'a, M: AutodiffModule<B>, B: AutodiffBackend> {
    grads: GradAdaptor,
    records: &'a mut AdamWRecord<M, B>,
    owned: Option<&'a HashSet<ParamId>>,
    /// Each slot's parameter and step number.
    ids: Vec<(ParamId, usize)>,
    slots: Vec<AdamWSlot<B::InnerBackend>>,
    /// Every gradient, owned or not, in module order: what the norm adds up.
    all: Vec<FloatTensor<B::InnerBackend>>,
    /// The module path being visited.
    path: Vec<String>,
    /// Each slot's module path, when asked for (once: they do not change between steps).
    names: Option<Vec<String>>,
}

impl<M: AutodiffModule<B>, B: AutodiffBackend> ModuleVisitor<B> for Gather<'_, M, B> {
    fn enter_module(&mut self, name: &str, _container: &str) {
        self.path.push(name.into());
    }

    fn exit_module(&mut self, _name: &str, _container: &str) {
        self.path.pop();
    }

    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        let Some((grad, device)) = self.grads.remove::<B::InnerBackend, D>(param.id) else {
            return;
        };
        if let Some(names) = self.names.as_mut() {
            names.push(self.path.join("."));
        }
        let grad = grad.into_primitive().tensor();
        self.all.push(grad.clone());
        if self.owned.is_some_and(|o| !o.contains(&param.id)) {
            return;
        }
        let tensor = param.val().inner().to_device(&device);
        let state = self.records.remove(&param.id).map(|r| {
            let s: AdamWState<B::InnerBackend, D> = r.into_state();
            <AdamW as SimpleOptimizer<B::InnerBackend>>::to_device(s, &device).momentum
        });
        let time = state.as_ref().map_or(0, |s| s.time) + 1;
        self.ids.push((param.id, time));
        self.slots.push(AdamWSlot {
            param: tensor.into_primitive().tensor(),
            grad,
            moments: state.map(|s| {
                let raw = |t: Tensor<B::InnerBackend, D>| t.into_primitive().tensor();
                (raw(s.moment_1), raw(s.moment_2))
            }),
            time,
        });
    }
}

/// A parameter's step: done by the kernel (new parameter and moments, step number), or still to take.
enum Outcome<B: Backend> {
    Done([FloatTensor<B>; 3], usize),
    Pending(AdamWSlot<B>),
}

/// Puts each parameter's new value in the module and its moments in the records.
struct Apply<'a, M: AutodiffModule<B>, B: AutodiffBackend> {
    outcomes: HashMap<ParamId, Outcome<B::InnerBackend>>,
    step: &'a AdamWStep<B::InnerBackend>,
    burn: AdamW,
    records: &'a mut AdamWRecord<M, B>,
}

impl<M: AutodiffModule<B>, B: AutodiffBackend> ModuleMapper<B> for Apply<'_, M, B> {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<B, D>>) -> Param<Tensor<B, D>> {
        let (id, tensor, mapper) = param.consume();
        let Some(outcome) = self.outcomes.remove(&id) else {
            return Param::from_mapped_value(id, tensor, mapper);
        };
        let typed = |t: FloatTensor<B::InnerBackend>| {
            Tensor::<B::InnerBackend, D>::from_primitive(TensorPrimitive::Float(t))
        };
        let (value, state) = match outcome {
            Outcome::Done([p, m, v], time) => {
                let momentum = AdaptiveMomentumState {
                    time,
                    moment_1: typed(m),
                    moment_2: typed(v),
                    max_moment_2: None,
                };
                (typed(p), AdamWState { momentum })
            }
            Outcome::Pending(slot) => {
                let mut grad = typed(slot.grad);
                if let Some(scale) = &self.step.grad_scale {
                    grad = grad * typed1(scale.clone()).reshape([1; D]);
                }
                let state = slot.moments.map(|(m, v)| AdamWState {
                    momentum: AdaptiveMomentumState {
                        time: slot.time - 1,
                        moment_1: typed(m),
                        moment_2: typed(v),
                        max_moment_2: None,
                    },
                });
                let old = (typed(slot.param.clone()), state.clone());
                let (p, s) = self.burn.step(self.step.lr, typed(slot.param), grad, state);
                let Some(mut s) = s else {
                    unreachable!("burn's AdamW always returns its state")
                };
                match skip_mask(self.step) {
                    Some(skip) => {
                        let m = &mut s.momentum;
                        let (m1, m2) = match old.1 {
                            Some(o) => (o.momentum.moment_1, o.momentum.moment_2),
                            None => (m.moment_1.zeros_like(), m.moment_2.zeros_like()),
                        };
                        m.moment_1 = unless_skipped(m.moment_1.clone(), m1, &skip);
                        m.moment_2 = unless_skipped(m.moment_2.clone(), m2, &skip);
                        (unless_skipped(p, old.0, &skip), s)
                    }
                    None => (p, s),
                }
            }
        };
        self.records.insert(id, AdaptorRecord::from_state(state));
        let mut value = Tensor::from_inner(value);
        if tensor.is_require_grad() {
            value = value.require_grad();
        }
        Param::from_mapped_value(id, value, mapper)
    }
}

#[cfg(test)]
#[path = "adamw_tests.rs"]
mod tests;
