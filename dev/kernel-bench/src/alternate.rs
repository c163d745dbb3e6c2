//! `umgen-kernel-bench train --alternate KEY=V1,V2`: steps that take turns between the values of one kernel setting
//! in one process, each value's steps timed apart.
//!
//! On an H100 the median step of one binary moved by about 20 ms between processes on one machine (226–246
//! ms for `small`), more than most kernel changes save; steps of one process agree far
//! better. The kernel choices are a value each step passes to the model (`train.kernels`), so one model
//! can run its steps under each value in turn.

use anyhow::{Context, bail};
use std::io::Write;
use std::path::Path;
use umgen::UmgenConfig;
use umgen::ops::Kernels;

/// The values of one setting and the kernels each gives.
pub(super) struct Alternation {
    key: String,
    values: Vec<String>,
    kernels: Vec<Kernels>,
}

/// What of a configuration decides the run (the model, its data and its maths): the whole configuration
/// with `train` replaced by [`TrainConfig::identity`], which leaves the kernel choices out.
fn identity(c: &UmgenConfig) -> serde_json::Value {
    let mut json = c.to_json();
    json["train"] = c.train.identity();
    json
}

impl Alternation {
    /// `spec` (`KEY=V1,V2[,…]`) applied after `sets` to the config at `path`, each value checked to change
    /// nothing but kernel choices against `base` (the config's loading checks that a run can use it).
    pub(super) fn parse(
        spec: &str,
        path: &Path,
        sets: &[String],
        base: &UmgenConfig,
    ) -> anyhow::Result<Self> {
        let (key, list) = spec
            .split_once('=')
            .with_context(|| format!("--alternate `{spec}`: expected KEY=V1,V2"))?;
        let values: Vec<String> = list
            .split(',')
            .map(str::trim)
            .filter(|v| !v.is_empty())
            .map(String::from)
            .collect();
        if values.len() < 2 {
            bail!("--alternate `{spec}`: give two or more values, KEY=V1,V2");
        }
        let reference = identity(base);
        let mut kernels = Vec::with_capacity(values.len());
        for value in &values {
            let mut layered = sets.to_vec();
            layered.push(format!("{key}={value}"));
            let (config, _) = UmgenConfig::load(path, &layered)
                .with_context(|| format!("--alternate {key}={value}"))?
                .without_missing_tokenizers();
            if identity(&config) != reference {
                bail!(
                    "--alternate {key}={value}: changes the model or the run, not only a kernel choice (those \
                     that alternate are under train.kernels: train.kernels.matmul, train.kernels.stream, …)"
                );
            }
            kernels.push(config.train.kernels);
        }
        Ok(Self {
            key: key.trim().to_string(),
            values,
            kernels,
        })
    }

    /// How many values take turns.
    pub(super) fn len(&self) -> usize {
        self.values.len()
    }

    /// The turn (the value's index) of step `step`.
    pub(super) fn turn(&self, step: usize) -> usize {
        step % self.kernels.len().max(1)
    }

    /// The kernels of turn `turn`.
    pub(super) fn kernels(&self, turn: usize) -> Kernels {
        self.kernels.get(turn).copied().unwrap_or_default()
    }

    /// One line per value: the median of its timed steps (`times[i]`, seconds), and its ratio to the first.
    pub(super) fn report(&self, out: &mut impl Write, times: &[Vec<f64>]) -> std::io::Result<()> {
        let medians: Vec<Option<f64>> = times
            .iter()
            .map(|t| umgen_cli::commands::bench_train::median(t.clone()))
            .collect();
        for ((value, median), t) in self.values.iter().zip(&medians).zip(times) {
            match (median, medians[0]) {
                (Some(m), Some(first)) => writeln!(
                    out,
                    "alternate     {}={value}: {:.1} ms (median of {} steps, {:.3}× the first value's)",
                    self.key,
                    1e3 * m,
                    t.len(),
                    m / first
                )?,
                _ => writeln!(out, "alternate     {}={value}: no timed step", self.key)?,
            }
        }
        Ok(())
    }
}
