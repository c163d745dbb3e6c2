//! `umgen-kernel-bench train --alternate KEY=V1,V2`: steps that take turns between the values of one kernel setting
//! in one process, each value's steps timed apart.
//!
//! On an H100 the median step of one binary moved by about 20 ms between processes on one machine (226–246
//! ms for `small`), more than most kernel changes save; steps of one process agree far
//! better. The kernel settings are process-wide choices read at every call (`TrainConfig::select_kernels`),
//! so one model can run its steps under each value in turn.

use anyhow::{Context, bail};
use std::io::Write;
use std::path::Path;
use umgen::UmgenConfig;
use umgen::train::TrainConfig;

/// The values of one setting and the training configuration each gives.
pub(super) struct Alternation {
    key: String,
    values: Vec<String>,
    configs: Vec<TrainConfig>,
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
    /// nothing but kernel choices against `base` and to be one `select_kernels` takes.
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
        let mut configs = Vec::with_capacity(values.len());
        for value in &values {
            let mut layered = sets.to_vec();
            layered.push(format!("{key}={value}"));
            let (config, _) = UmgenConfig::load(path, &layered)
                .with_context(|| format!("--alternate {key}={value}"))?
                .without_missing_tokenizers();
            if identity(&config) != reference {
                bail!(
                    "--alternate {key}={value}: changes the model or the run, not only a kernel choice (those \
                     that alternate: train.matmul, train.attention, train.attention_step, \
                     train.attention_block_mib, train.recompute, train.norm, train.gelu, train.xent, train.kernel_stream, \
                     train.adamw, train.launch_thread)"
                );
            }
            config
                .train
                .select_kernels()
                .with_context(|| format!("--alternate {key}={value}"))?;
            configs.push(config.train);
        }
        Ok(Self {
            key: key.trim().to_string(),
            values,
            configs,
        })
    }

    /// How many values take turns.
    pub(super) fn len(&self) -> usize {
        self.values.len()
    }

    /// Selects the kernels of step `step`'s value and returns its index.
    pub(super) fn select(&self, step: usize) -> anyhow::Result<usize> {
        let i = step % self.configs.len();
        self.configs[i].select_kernels()?;
        Ok(i)
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
