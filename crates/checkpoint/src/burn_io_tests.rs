//! [`super`]'s round trips: weights and optimizer state through bytes, resumed training, refusals.

use super::*;
use burn::nn::{Linear, LinearConfig};
use burn::optim::{AdamWConfig, GradientsParams};

type B = burn::backend::Autodiff<burn::backend::Flex>;

#[derive(Module, Debug)]
struct Net<B: Backend> {
    a: Linear<B>,
    b: Linear<B>,
}

fn net(dev: &burn::tensor::Device<B>) -> Net<B> {
    stable_param_ids(Net {
        a: LinearConfig::new(3, 4).init(dev),
        b: LinearConfig::new(4, 2).init(dev),
    })
}

fn step(m: Net<B>, o: &mut impl Optimizer<Net<B>, B>) -> Net<B> {
    let dev = Default::default();
    let x = Tensor::<B, 2>::ones([2, 3], &dev);
    let loss = m.b.forward(m.a.forward(x)).powf_scalar(2.0).sum();
    let g = GradientsParams::from_grads(loss.backward(), &m);
    o.step(1e-2, m, g)
}

#[test]
fn ids_follow_paths_and_training_resumes_exactly() {
    let dev = Default::default();
    let (m1, m2) = (net(&dev), net(&dev));
    assert_eq!(m1.a.weight.id, m2.a.weight.id);
    assert_ne!(m1.a.weight.id, m1.b.weight.id);
    // Two steps straight vs. one step, save, restore into a fresh model and optimizer, one step.
    let mut o = AdamWConfig::new().init();
    let straight = step(step(m1.clone(), &mut o), &mut o);
    let mut o1 = AdamWConfig::new().init();
    let after1 = step(m1, &mut o1);
    let (w, s) = (
        weights_to_bytes(&after1).unwrap(),
        optimizer_to_bytes(&o1).unwrap(),
    );
    let restored = weights_from_bytes(net(&dev), w, "net").unwrap();
    let mut o2 = optimizer_from_bytes(AdamWConfig::new().init(), s, &dev).unwrap();
    let resumed = step(restored, &mut o2);
    let (a, b) = (
        straight.b.weight.val().into_data(),
        resumed.b.weight.val().into_data(),
    );
    assert_eq!(a, b);
    assert!(
        weights_to_bytes(&straight).unwrap() == weights_to_bytes(&resumed).unwrap(),
        "equal weights, equal bytes"
    );
}

#[test]
fn optimizer_state_goes_through_items_and_loads_in_part() {
    type Entry = burn::optim::record::AdaptorRecord<burn::optim::AdamW, B>;
    let dev = Default::default();
    let mut o = AdamWConfig::new().init();
    let m = step(step(net(&dev), &mut o), &mut o);
    let whole: HashMap<ParamId, Entry> = o.to_record().into_iter().collect();
    assert_eq!(whole.len(), 4);
    // Entry by entry into items, then bytes: what `optimizer_to_bytes` reads back.
    let items = whole
        .clone()
        .into_iter()
        .map(|(id, r)| (id, r.into_item::<FullPrecisionSettings>()));
    let bytes = optimizer_items_to_bytes::<B, Entry>(items).unwrap();
    let (mut o1, mut o2) = (
        optimizer_from_bytes(AdamWConfig::new().init(), bytes.clone(), &dev).unwrap(),
        optimizer_from_bytes(AdamWConfig::new().init(), optimizer_to_bytes(&o).unwrap(), &dev).unwrap(),
    );
    let (a, b) = (step(m.clone(), &mut o1), step(m.clone(), &mut o2));
    assert!(weights_to_bytes(&a).unwrap() == weights_to_bytes(&b).unwrap());
    // In part: only the entries asked for, with their values.
    let keep = [m.a.weight.id, m.b.bias.as_ref().unwrap().id];
    let part: HashMap<ParamId, Entry> =
        optimizer_records_from_bytes(&bytes, &dev, |id| keep.contains(&id)).unwrap();
    assert_eq!(part.len(), 2);
    for id in keep {
        let (x, y) = (part[&id].clone(), whole[&id].clone());
        let x = x.into_item::<FullPrecisionSettings>();
        let y = y.into_item::<FullPrecisionSettings>();
        assert_eq!(
            format!("{:?}", serde_json::to_value(&x).unwrap()),
            format!("{:?}", serde_json::to_value(&y).unwrap())
        );
    }
    let garbage = optimizer_records_from_bytes::<B, Entry, Vec<_>>(&[1, 2, 3], &dev, |_| true);
    assert!(garbage.is_err());
    let err = optimizer_from_bytes(AdamWConfig::new().init::<B, Net<B>>(), vec![9; 5], &dev).err();
    assert!(err.is_some_and(|e| e.to_string().contains("optimizer state")));
}

#[test]
fn mismatched_weights_are_refused() {
    let dev = Default::default();
    #[derive(Module, Debug)]
    struct Other<B: Backend> {
        a: Linear<B>,
    }
    let other = Other::<B> {
        a: LinearConfig::new(3, 4).init(&dev),
    };
    let bytes = weights_to_bytes(&other).unwrap();
    let err = weights_from_bytes(net(&dev), bytes, "net")
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("net") && err.contains("missing") && err.contains("b.weight"),
        "{err}"
    );
}

#[test]
fn non_finite_weights_are_found_by_name_in_every_float_type() {
    let file = |dtype: Dtype, bytes: Vec<u8>| {
        let n = bytes.len() * 8 / dtype.bitsize();
        let ok = vec![0u8; bytes.len()];
        let views = vec![
            ("a.ok", TensorView::new(dtype, vec![n], &ok).unwrap()),
            ("b.bad", TensorView::new(dtype, vec![n], &bytes).unwrap()),
        ];
        safetensors::serialize(views, None).unwrap()
    };
    let f32s = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    assert_eq!(
        first_non_finite(&file(Dtype::F32, f32s(&[1.0, -3e38]))).unwrap(),
        None
    );
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        let found = first_non_finite(&file(Dtype::F32, f32s(&[1.0, bad]))).unwrap();
        assert_eq!(found.as_deref(), Some("b.bad"), "{bad}");
    }
    // bf16: the f32's high half; f16: 0x7c00 is +inf, 0x7e00 NaN, 0x7bff the largest finite value.
    let halves = |v: &[u16]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    let bf16 = |x: f32| (x.to_bits() >> 16) as u16;
    assert_eq!(
        first_non_finite(&file(Dtype::BF16, halves(&[bf16(3e38)]))).unwrap(),
        None
    );
    assert!(
        first_non_finite(&file(Dtype::BF16, halves(&[bf16(f32::NAN)])))
            .unwrap()
            .is_some()
    );
    assert_eq!(
        first_non_finite(&file(Dtype::F16, halves(&[0x7bff]))).unwrap(),
        None
    );
    assert!(
        first_non_finite(&file(Dtype::F16, halves(&[0x7c00])))
            .unwrap()
            .is_some()
    );
    assert!(first_non_finite(b"not safetensors").is_err());
}
