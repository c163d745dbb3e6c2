//! `umgen-kernel-bench train`: `umgen bench train`'s steps with the developer hooks: kernel settings that
//! take turns within one process ([`crate::alternate`]) and a profile of the host ([`crate::host_profile`]).

use crate::alternate::Alternation;
use crate::args::TrainArgs;
use crate::host_profile::HostProfile;
use std::io::Write;
use umgen::ops::Kernels;
use umgen_cli::commands::bench::bench_config;
use umgen_cli::commands::bench_train::{StepHooks, run_with};

/// The hooks: the alternation (if any) and the profile being taken.
struct Hooks {
    alternation: Option<Alternation>,
    profile: Option<std::path::PathBuf>,
    taking: Option<HostProfile>,
}

impl StepHooks for Hooks {
    fn turns(&self) -> usize {
        self.alternation.as_ref().map_or(1, Alternation::len)
    }

    fn before_step(&mut self, i: usize) -> anyhow::Result<usize> {
        Ok(self.alternation.as_ref().map_or(0, |a| a.turn(i)))
    }

    fn kernels(&self, turn: usize, base: &Kernels) -> Kernels {
        self.alternation.as_ref().map_or(*base, |a| a.kernels(turn))
    }

    fn timed(&mut self, start: bool) -> anyhow::Result<()> {
        if start {
            self.taking = Some(HostProfile::start(self.profile.clone())?);
        } else if let Some(p) = self.taking.take() {
            p.finish()?;
        }
        Ok(())
    }

    fn report(&self, mut out: &mut dyn Write, by_turn: &[Vec<f64>]) -> anyhow::Result<()> {
        if let Some(a) = &self.alternation {
            a.report(&mut out, by_turn)?;
        }
        Ok(())
    }
}

/// Runs the steps.
pub fn run(a: &TrainArgs) -> anyhow::Result<()> {
    let b = &a.bench;
    let alternation = match &a.alternate {
        Some(spec) => {
            let (config, path, sets) = bench_config(&b.model)?;
            Some(Alternation::parse(spec, &path, &sets, &config)?)
        }
        None => None,
    };
    let mut hooks = Hooks {
        alternation,
        profile: a.host_profile.clone(),
        taking: None,
    };
    run_with(b, &umgen_cli::Kinds::default(), &mut hooks)
}
