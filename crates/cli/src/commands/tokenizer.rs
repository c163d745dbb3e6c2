//! `umgen tokenizer train` and `umgen tokenizer eval`.

use crate::cli::{TokenizerCommand, TokenizerEvalArgs, TokenizerTrainArgs};
use crate::device::Device;
use crate::dist::rank_device;
use anyhow::Context;
use burn::tensor::backend::AutodiffBackend;
use std::io::Write;
use std::ops::ControlFlow;
use std::path::PathBuf;
use umgen::data::Dataset;
use umgen::dist::DistEnv;
use umgen::tokenizer_vq::{IouCounter, Output, PsnrCounter, RasterSource, code_stats, train_on};
use umgen::{DatasetRasters, UmgenConfig, VqTarget, vq_target};

/// Runs a tokenizer subcommand.
pub fn run(command: TokenizerCommand) -> anyhow::Result<()> {
    match command {
        TokenizerCommand::Train(a) => train_cmd(&a),
        TokenizerCommand::Eval(a) => eval(&a),
    }
}

/// The rasters of `split` (every `stride`-th frame), refused when there are none.
fn split_rasters<'a>(
    data: &'a Dataset,
    target: &'a VqTarget,
    dir: &std::path::Path,
    split: &str,
    stride: usize,
) -> anyhow::Result<DatasetRasters<'a>> {
    let source = DatasetRasters::new(data, target.view.as_ref(), Some(split), stride);
    anyhow::ensure!(
        !source.is_empty(),
        "{}: no frames in split `{split}`",
        dir.display()
    );
    Ok(source)
}

fn train_cmd(a: &TokenizerTrainArgs) -> anyhow::Result<()> {
    let env = DistEnv::from_env()?;
    let lead = env.rank == 0;
    let t = &a.target;
    let config = UmgenConfig::load(&t.config.config, &t.config.set)?;
    let target = vq_target(&config, &t.modality)?;
    let data = Dataset::open(&t.data)?;
    let source = split_rasters(&data, &target, &t.data, &a.split, a.stride)?;
    let out = a
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from(format!("runs/tokenizer-{}", t.modality)));
    let [c, h, w] = source.shape();
    tracing::info!(
        "training the `{}` tokenizer on {} rasters of {c}×{h}×{w} from {} ({} steps of {} × {} rank(s)) into {}",
        t.modality,
        source.len(),
        t.data.display(),
        target.train.steps,
        target.train.batch_size,
        env.world_size,
        out.display()
    );
    let bar = if lead {
        crate::progress::bar(target.train.steps, "steps")?
    } else {
        indicatif::ProgressBar::hidden()
    };
    let device = Device::parse(&rank_device(&a.device, &env))?;
    // Ranks must train the same tokenizer: the digest covers what shapes the run.
    let identity = umgen::checkpoint::sha256(
        serde_json::json!({"modality": t.modality, "vq": target.vq, "train": target.train, "raster": [c, h, w]})
            .to_string()
            .as_bytes(),
    );
    let started = std::time::Instant::now();
    let limit = crate::progress::TimeLimit::minutes(a.time_limit);
    let info = crate::with_autodiff!(device, |B, dev| {
        let mut group = crate::dist::join::<<B as AutodiffBackend>::InnerBackend>(&env, &identity, &a.dist)?;
        let tok = train_on::<B>(
            &target.vq,
            &target.train,
            &source,
            &out,
            &dev,
            group.as_mut(),
            |r| {
                bar.set_position(r.step);
                if let Some(v) = &r.values {
                    let line: Vec<String> = v.iter().map(|(k, x)| format!("{k} {x:.4}")).collect();
                    bar.set_message(format!("loss {:.4}", v[0].1));
                    bar.suspend(|| tracing::info!("step {}/{}: {}", r.step, r.steps, line.join(", ")));
                }
                if limit.reached(&bar, r.step) {
                    return ControlFlow::Break(());
                }
                ControlFlow::Continue(())
            },
        )?;
        group.finish();
        tok.info().clone()
    });
    bar.finish_and_clear();
    tracing::info!(
        "{}: tokenizer of {} steps in {:.0} s; codebook usage {:.1}%, perplexity {:.0}; set `modality.{}.tokenizer = \"{}\"`",
        out.display(),
        info.steps,
        started.elapsed().as_secs_f64(),
        100.0 * info.usage,
        info.perplexity,
        t.modality,
        out.display()
    );
    Ok(())
}

fn eval(a: &TokenizerEvalArgs) -> anyhow::Result<()> {
    let t = &a.target;
    let config = UmgenConfig::load(&t.config.config, &t.config.set)?;
    let target = vq_target(&config, &t.modality)?;
    let dir = a
        .tokenizer
        .clone()
        .or(target.tokenizer.clone())
        .with_context(|| {
            format!(
                "no tokenizer: pass --tokenizer or set `modality.{}.tokenizer`",
                t.modality
            )
        })?;
    let data = Dataset::open(&t.data)?;
    let source = split_rasters(&data, &target, &t.data, &a.split, 1)?;
    let codec = Device::parse(&a.device)?.codec_loader()(&dir)?;
    let [c, h, w] = source.shape();
    let f = target.vq.downsampling();
    let n = a.frames.clamp(1, source.len());
    let picks: Vec<usize> = (0..n).map(|i| i * source.len() / n).collect();
    let (mut iou, mut psnr, mut ids_all) = (IouCounter::default(), PsnrCounter::default(), Vec::new());
    let out = a.out.clone().unwrap_or_else(|| dir.join("eval"));
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let bar = crate::progress::bar(n as u64, "frames")?;
    for (b, chunk) in picks.chunks(16).enumerate() {
        let input = umgen::tokenizer_vq::render(&source, chunk, 4)?;
        let ids = codec.encode(input.clone(), chunk.len(), [h, w])?;
        let recon = codec.decode(&ids, chunk.len(), [h / f, w / f])?;
        match target.vq.output {
            Output::Binary => iou.add(c, [h, w], &recon, &input),
            Output::Rgb => psnr.add(&recon, &input),
        }
        if b == 0 {
            for k in 0..chunk.len().min(6) {
                let plane = c * h * w;
                let pic = side_by_side(
                    target.vq.output,
                    [c, h, w],
                    &input[k * plane..(k + 1) * plane],
                    &recon[k * plane..(k + 1) * plane],
                );
                umgen_viz::write_png(&out.join(format!("recon-{k:02}.png")), &pic)?;
            }
        }
        ids_all.extend(ids);
        bar.inc(chunk.len() as u64);
    }
    bar.finish_and_clear();
    let (usage, perplexity) = code_stats(&ids_all, target.vq.codebook_size);
    let mut report = serde_json::json!({
        "modality": t.modality, "tokenizer": dir, "data": t.data, "split": a.split, "frames": n,
        "codebook_usage": usage, "perplexity": perplexity,
    });
    let mut stdout = std::io::stdout().lock();
    writeln!(
        stdout,
        "{} tokenizer {} on {} frames of {} `{}`",
        t.modality,
        dir.display(),
        n,
        t.data.display(),
        a.split
    )?;
    match target.vq.output {
        Output::Binary => {
            let (exact, near) = (iou.iou(), iou.near());
            let mut per = Vec::new();
            for (k, ((v, n), p)) in exact.iter().zip(&near).zip(iou.positives()).enumerate() {
                let shown = v.map_or_else(|| "absent".to_string(), |x| format!("{x:.4}"));
                let within = n.map_or_else(String::new, |n| {
                    format!(
                        "; within 1 px: precision {:.4}, recall {:.4}, F1 {:.4}",
                        n.precision, n.recall, n.f1
                    )
                });
                writeln!(
                    stdout,
                    "  channel {k}: IoU {shown}  ({p} positive pixels){within}"
                )?;
                per.push(serde_json::json!({
                    "iou": v,
                    "positive_pixels": p,
                    "within_1px": n.map(|n| serde_json::json!({"precision": n.precision, "recall": n.recall, "f1": n.f1})),
                }));
            }
            report["channels"] = per.into();
        }
        Output::Rgb => {
            writeln!(stdout, "  PSNR {:.2} dB", psnr.psnr())?;
            report["psnr_db"] = psnr.psnr().into();
        }
    }
    writeln!(
        stdout,
        "  codebook usage {:.1}%, perplexity {:.1}",
        100.0 * usage,
        perplexity
    )?;
    let path = out.join("report.json");
    std::fs::write(&path, serde_json::to_vec_pretty(&report)?)
        .with_context(|| format!("writing {}", path.display()))?;
    tracing::info!("{}: report and pictures", out.display());
    Ok(())
}

/// Input | reconstruction, side by side.
fn side_by_side(output: Output, [c, h, w]: [usize; 3], input: &[f32], recon: &[f32]) -> umgen_viz::Rgb {
    let mut pic = umgen_viz::Rgb::filled(2 * w + 4, h, [255, 255, 255]);
    for (side, values) in [input, recon].into_iter().enumerate() {
        for r in 0..h {
            for col in 0..w {
                let px = match output {
                    Output::Rgb => [0, 1, 2]
                        .map(|k| ((values[(k * h + r) * w + col].clamp(-1.0, 1.0) + 1.0) * 127.5) as u8),
                    Output::Binary => {
                        let mut p = umgen_viz::BACKGROUND;
                        for (k, layer) in umgen::scene::MapLayer::ALL.iter().enumerate().take(c) {
                            if values[(k * h + r) * w + col] > 0.5 {
                                p = umgen_viz::layer_colour(*layer);
                            }
                        }
                        p
                    }
                };
                pic.pixels[r * pic.width + side * (w + 4) + col] = px;
            }
        }
    }
    pic
}
