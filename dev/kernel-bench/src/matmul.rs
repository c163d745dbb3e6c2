//! `umgen-kernel-bench matmul`: the matrix-product kernels that cubecl offers, timed one by one on the shapes of
//! a training step. Without the `autotune` build every product runs burn's default kernel; this says how
//! much a better choice would gain per shape and number format before anything is wired to pick it.

use crate::args::BenchMatmulArgs;
use anyhow::Context;

/// One product: `batch` independent `[m, k] × [k, n]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Shape {
    pub(super) batch: usize,
    pub(super) m: usize,
    pub(super) k: usize,
    pub(super) n: usize,
}

impl Shape {
    /// `[BATCHx]MxKxN`.
    pub(super) fn parse(s: &str) -> anyhow::Result<Self> {
        let v: Vec<usize> = s
            .split('x')
            .map(|x| x.parse::<usize>())
            .collect::<Result<_, _>>()
            .with_context(|| format!("--shapes `{s}`: expected [BATCHx]MxKxN"))?;
        let shape = match v[..] {
            [m, k, n] => Self { batch: 1, m, k, n },
            [batch, m, k, n] => Self { batch, m, k, n },
            _ => anyhow::bail!("--shapes `{s}`: expected three or four sizes, [BATCHx]MxKxN"),
        };
        anyhow::ensure!(v.iter().all(|&x| x > 0), "--shapes `{s}`: sizes must be positive");
        Ok(shape)
    }

    /// Multiply-adds × 2.
    pub(super) fn flops(&self) -> f64 {
        2.0 * (self.batch * self.m * self.k * self.n) as f64
    }
}

/// A kernel's refusal on one line of at most `max` characters, for a table row.
#[cfg(feature = "cuda")]
pub(super) fn one_line(e: &str, max: usize) -> String {
    e.split_whitespace()
        .collect::<Vec<_>>()
        .join(" ")
        .chars()
        .take(max)
        .collect()
}

/// Measures (CUDA builds only).
pub fn run(a: &BenchMatmulArgs) -> anyhow::Result<()> {
    let shapes: Vec<Shape> = a
        .shapes
        .iter()
        .map(|s| Shape::parse(s))
        .collect::<Result<_, _>>()?;
    anyhow::ensure!(a.iters > 0, "--iters must be at least 1");
    let device = umgen_cli::device::Device::parse(&a.device)?;
    match device {
        #[cfg(feature = "cuda")]
        umgen_cli::device::Device::Cuda(i) => cuda::run(a, &shapes, i),
        _ => anyhow::bail!(
            "`bench matmul` times cubecl's CUDA kernels: it needs --device cuda:N (got `{}`; {} shape(s) \
             parsed)",
            a.device,
            shapes.len()
        ),
    }
}

#[cfg(feature = "cuda")]
mod cuda {
    use super::{BenchMatmulArgs, Shape};
    use crate::args::PrecisionArg;
    use burn::backend::cuda::CudaDevice;
    use burn::cubecl::cuda::CudaRuntime;
    use burn::tensor::backend::Backend;
    use burn::tensor::{DType, Distribution, FloatDType, Tensor, TensorPrimitive};
    use cubek::matmul::components::tile::TileMatmulKind;
    use cubek::matmul::launch::Strategy;
    use cubek::matmul::routines::BlueprintStrategy;
    use cubek::matmul::routines::double_buffering::DoubleBufferingArgs;
    use cubek::matmul::routines::ordered_double_buffering::OrderedSelectionArgs;
    use cubek::matmul::routines::simple::SimpleArgs;
    use std::io::Write;
    use std::time::Instant;
    use umgen::ops::matmul::launch_kernel;

    type Cb = burn_cubecl::CubeBackend<CudaRuntime, f32, i32, u8>;
    type Primitive = burn_cubecl::tensor::CubeTensor<CudaRuntime>;

    /// The kernels burn's autotuning chooses between for tensor-core products, plus its default
    /// (`Strategy::Auto`, what runs without autotuning).
    fn candidates() -> Vec<Strategy> {
        let simple = |multi_rows, tile_matmul| SimpleArgs {
            multi_rows,
            tile_matmul,
        };
        let ordered = |row_count, tile_matmul| OrderedSelectionArgs {
            partition_k: Some(2),
            row_count: Some(row_count),
            rows_per_plane: Some(2),
            tile_matmul,
        };
        let double = |specialized, tile_matmul| DoubleBufferingArgs {
            specialized,
            tile_matmul,
        };
        let (c, m) = (TileMatmulKind::Cmma, TileMatmulKind::Mma);
        vec![
            Strategy::Auto,
            Strategy::SimpleCyclicCmma(BlueprintStrategy::Inferred(simple(true, c))),
            Strategy::SimpleCyclicMma(BlueprintStrategy::Inferred(simple(false, m))),
            Strategy::SimpleCyclicMma(BlueprintStrategy::Inferred(simple(true, m))),
            Strategy::OrderedDoubleCmma(BlueprintStrategy::Inferred(ordered(4, c))),
            Strategy::OrderedDoubleMma(BlueprintStrategy::Inferred(ordered(4, m))),
            Strategy::OrderedDoubleCmma(BlueprintStrategy::Inferred(ordered(8, c))),
            Strategy::OrderedDoubleMma(BlueprintStrategy::Inferred(ordered(8, m))),
            Strategy::DoubleCyclicCmma(BlueprintStrategy::Inferred(double(false, c))),
            Strategy::DoubleCyclicMma(BlueprintStrategy::Inferred(double(false, m))),
            Strategy::DoubleCyclicCmma(BlueprintStrategy::Inferred(double(true, c))),
            Strategy::DoubleCyclicMma(BlueprintStrategy::Inferred(double(true, m))),
            Strategy::SpecializedCyclicCmma(BlueprintStrategy::Inferred(().into())),
            Strategy::SpecializedCyclicMma(BlueprintStrategy::Inferred(().into())),
            Strategy::SimpleTmaCmma(BlueprintStrategy::Inferred(simple(false, c))),
            Strategy::SimpleTmaMma(BlueprintStrategy::Inferred(simple(false, m))),
            Strategy::SimpleTmaMma(BlueprintStrategy::Inferred(simple(true, m))),
            Strategy::SpecializedTmaCmma(BlueprintStrategy::Inferred(().into())),
            Strategy::SpecializedTmaMma(BlueprintStrategy::Inferred(().into())),
        ]
    }

    fn name(s: &Strategy) -> String {
        match s {
            Strategy::Auto => "auto (burn's default)".to_string(),
            s => s.to_string(),
        }
    }

    fn float(t: Primitive) -> Tensor<Cb, 3> {
        Tensor::from_primitive(TensorPrimitive::Float(t))
    }

    /// Largest |difference| / largest |reference|, in f32.
    fn rel_err(x: &Primitive, reference: &Primitive) -> f64 {
        let f32_of = |t: &Primitive| float(t.clone()).cast(FloatDType::F32);
        crate::attention::rel_err(f32_of(x), f32_of(reference))
    }

    pub(super) fn run(a: &BenchMatmulArgs, shapes: &[Shape], gpu: usize) -> anyhow::Result<()> {
        let dev = CudaDevice::new(gpu);
        let kernels: Vec<Strategy> = candidates()
            .into_iter()
            .filter(|s| a.kernels.is_empty() || a.kernels.iter().any(|k| name(s).contains(k.as_str())))
            .collect();
        anyhow::ensure!(
            !kernels.is_empty(),
            "--kernels {:?} names none of the kernels",
            a.kernels
        );
        let start = Instant::now();
        let mut out = std::io::stdout().lock();
        writeln!(
            out,
            "matmul kernels on cuda:{gpu}, median of {} launches; TFLOP/s = 2·batch·m·k·n / time; err = max|Δ| / \
             max|auto| (f32 operands run as TF32 on the tensor cores)",
            a.iters
        )?;
        writeln!(
            out,
            "{:<20} {:<5} {:<64} {:>10} {:>9} {:>9}",
            "shape", "dtype", "kernel", "ms", "TFLOP/s", "err"
        )?;
        for (shape, text) in shapes.iter().zip(&a.shapes) {
            for &p in &a.dtypes {
                let dtype = match p {
                    PrecisionArg::F32 => FloatDType::F32,
                    PrecisionArg::Bf16 => FloatDType::BF16,
                };
                let Shape { batch, m, k, n } = *shape;
                let dist = Distribution::Normal(0.0, 1.0);
                let lhs = Tensor::<Cb, 3>::random([batch, m, k], dist, &dev).cast(dtype);
                let rhs = Tensor::<Cb, 3>::random([batch, k, n], dist, &dev).cast(dtype);
                let (lhs, rhs) = (lhs.into_primitive().tensor(), rhs.into_primitive().tensor());
                let mut reference: Option<Primitive> = None;
                for s in &kernels {
                    if start.elapsed().as_secs_f64() > a.seconds {
                        writeln!(out, "stopped after --seconds {}", a.seconds)?;
                        return Ok(());
                    }
                    let o = burn_cubecl::kernel::matmul::init_matmul_output(&lhs, &rhs, DType::from(dtype));
                    let row = time(s, &lhs, &rhs, &o, a.iters, &dev);
                    let (ms, tflops, err) = match row {
                        Ok(secs) => {
                            let err = reference.as_ref().map_or(0.0, |r| rel_err(&o, r));
                            if reference.is_none() {
                                reference = Some(o);
                            }
                            (
                                format!("{:.3}", 1e3 * secs),
                                format!("{:.1}", shape.flops() / secs / 1e12),
                                format!("{err:.1e}"),
                            )
                        }
                        Err(e) => (String::from("-"), String::from("-"), super::one_line(&e, 80)),
                    };
                    writeln!(
                        out,
                        "{text:<20} {:<5} {:<64} {ms:>10} {tflops:>9} {err:>9}",
                        p.name(),
                        name(s)
                    )?;
                    out.flush()?;
                }
            }
        }
        Ok(())
    }

    /// Median seconds of one launch after one untimed launch (which compiles the kernel).
    fn time(
        s: &Strategy,
        lhs: &Primitive,
        rhs: &Primitive,
        o: &Primitive,
        iters: usize,
        dev: &CudaDevice,
    ) -> Result<f64, String> {
        launch_kernel(s, lhs, rhs, o)?;
        Cb::sync(dev).map_err(|e| format!("{e:?}"))?;
        let mut t = Vec::with_capacity(iters);
        for _ in 0..iters {
            let t0 = Instant::now();
            launch_kernel(s, lhs, rhs, o)?;
            Cb::sync(dev).map_err(|e| format!("{e:?}"))?;
            t.push(t0.elapsed().as_secs_f64());
        }
        t.sort_by(f64::total_cmp);
        Ok(t[t.len() / 2])
    }
}

#[cfg(test)]
mod tests {
    use super::Shape;
    use crate::args::{BenchMatmulArgs, PrecisionArg};

    fn args(device: &str, shapes: &[&str]) -> BenchMatmulArgs {
        BenchMatmulArgs {
            device: device.into(),
            shapes: shapes.iter().map(|s| s.to_string()).collect(),
            dtypes: vec![PrecisionArg::F32],
            kernels: vec![],
            iters: 1,
            seconds: 1.0,
        }
    }

    #[test]
    fn bad_shapes_and_the_cpu_are_refused_by_name() {
        let e = super::run(&args("cpu", &["2x3x4"])).unwrap_err().to_string();
        assert!(e.contains("cuda:N") && e.contains("`cpu`"), "{e}");
        let e = super::run(&args("cuda:0", &["2x3x4", "7x7"]))
            .unwrap_err()
            .to_string();
        assert!(e.contains("`7x7`"), "{e}");
    }

    #[test]
    fn shapes_parse_with_and_without_batch() {
        assert_eq!(
            Shape::parse("2x3x4x5").unwrap(),
            Shape {
                batch: 2,
                m: 3,
                k: 4,
                n: 5
            }
        );
        assert_eq!(
            Shape::parse("3x4x5").unwrap(),
            Shape {
                batch: 1,
                m: 3,
                k: 4,
                n: 5
            }
        );
        assert_eq!(Shape::parse("3x4x5").unwrap().flops(), 120.0);
        for bad in ["3x4", "3x0x5", "ax4x5", "1x2x3x4x5"] {
            let e = Shape::parse(bad).unwrap_err().to_string();
            assert!(e.contains(bad), "{e}");
        }
    }
}
