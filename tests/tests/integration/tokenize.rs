//! The tokenize pipeline end to end: train tiny tokenizers, tokenize a dataset, skip finished shards,
//! read windows back and decode them into frames.

use umgen::data::{Dataset, TokenSet};
use umgen::{UmgenConfig, builtin_catalog, tokenize_dataset};
use umgen_tests::fixtures::{tiny_dataset, train_tokenizers};

fn config(tokenizers: Option<&std::path::Path>) -> UmgenConfig {
    let tok = |m: &str| {
        tokenizers.map_or(String::new(), |d| {
            format!("tokenizer = \"{}\"\n", d.join(m).display())
        })
    };
    let text = format!(
        "[layout]\norder = [\"ego\", \"map\", \"agent\", \"image\"]\n\
         [modality.agent]\nmax_agents = 4\n\
         [modality.map]\nraster = [32, 32]\ngrid = [4, 4]\ncodebook_size = 32\n{}\
         [modality.map.vq]\nbase = 8\nmult = [1, 2, 2, 2]\nres_blocks = 1\nz_channels = 4\nembed_dim = 4\nattention = false\ngroups = 4\n\
         [modality.map.vq_train]\nsteps = 2\nbatch_size = 2\nthreads = 1\n\
         [modality.image]\nsize = [32, 64]\ngrid = [2, 4]\ncodebook_size = 32\n{}\
         [modality.image.vq]\nbase = 8\nmult = [1, 1, 2, 2, 2]\nres_blocks = 1\nz_channels = 4\nembed_dim = 4\nattention = false\ngroups = 4\n\
         [modality.image.vq_train]\nsteps = 2\nbatch_size = 2\nthreads = 1\n",
        tok("map"),
        tok("image")
    );
    UmgenConfig::from_toml_str(&text).unwrap()
}

#[test]
fn a_dataset_tokenizes_reads_back_and_decodes() {
    let dir = tempfile::tempdir().unwrap();
    let ds_dir = tiny_dataset(dir.path(), 12).unwrap();
    let data = Dataset::open(&ds_dir).unwrap();
    train_tokenizers(&config(None), &data, &dir.path().join("tok")).unwrap();
    let cfg = config(Some(&dir.path().join("tok")));
    let registry = cfg.registry(&builtin_catalog().unwrap()).unwrap();
    let layout = registry.layout().unwrap();
    assert_eq!(layout.len(), 5 + 18 + 46 + 10);
    let out = dir.path().join("tokens");
    let first = tokenize_dataset(std::slice::from_ref(&registry), &data, &out, None, 2, |_, _| {}).unwrap();
    let frames: usize = data.clips().iter().map(|c| c.frames).sum();
    assert_eq!((first.written, first.skipped, first.frames), (1, 0, frames));
    let again = tokenize_dataset(std::slice::from_ref(&registry), &data, &out, None, 2, |_, _| {}).unwrap();
    assert_eq!(
        (again.written, again.skipped),
        (0, 1),
        "finished shards are skipped"
    );
    // Two registries (one per device) share the threads and write the same cache as one.
    let out2 = dir.path().join("tokens-2");
    let two = [
        cfg.registry(&builtin_catalog().unwrap()).unwrap(),
        cfg.registry(&builtin_catalog().unwrap()).unwrap(),
    ];
    tokenize_dataset(&two, &data, &out2, None, 2, |_, _| {}).unwrap();
    let shards = |d: &std::path::Path| -> Vec<(std::ffi::OsString, Vec<u8>)> {
        let mut v: Vec<_> = std::fs::read_dir(d.join("shards"))
            .unwrap()
            .map(|e| e.unwrap())
            .map(|e| (e.file_name(), std::fs::read(e.path()).unwrap()))
            .collect();
        v.sort();
        v
    };
    assert!(!shards(&out).is_empty());
    assert_eq!(shards(&out), shards(&out2));
    let set = TokenSet::open(&out, layout.fingerprint()).unwrap();
    let windows = set.windows(3, 1, Some("train"));
    assert_eq!(windows.len(), data.windows(3, 1, Some("train")).len());
    let rows = set.read(windows[0], 3, 1).unwrap();
    // The cached row equals tokenizing the same clip again, and decodes into a frame.
    let clip = data
        .read_window(windows[0].clip, 0, data.clips()[windows[0].clip].frames, 1)
        .unwrap();
    let fresh = registry.tokenize_clip(&clip).unwrap();
    assert_eq!(&rows[..layout.len()], &fresh[0][..]);
    let mut frame = umgen::scene::Frame::default();
    registry.detokenize(&rows[..layout.len()], &mut frame).unwrap();
    let map = frame.map.as_ref().unwrap();
    assert_eq!((map.channels, map.height, map.width), (6, 32, 32));
    let image = frame.image.as_ref().unwrap();
    assert_eq!((image.height, image.width), (32, 64));
    assert_eq!(
        frame.agents.len(),
        clip.frames[0].agents.len(),
        "agents decode slot by slot"
    );
    // Without the rasters' kinds, the same frame less its map and image.
    let mut light = umgen::scene::Frame::default();
    registry
        .detokenize_except(&rows[..layout.len()], &mut light, &["map", "image"])
        .unwrap();
    assert!(light.map.is_none() && light.image.is_none());
    let stripped = umgen::scene::Frame {
        map: None,
        image: None,
        ..frame.clone()
    };
    assert_eq!(light, stripped);
    // A cache made for this layout is refused by another one.
    let other = UmgenConfig::from_toml_str("[layout]\norder = [\"ego\"]")
        .unwrap()
        .registry(&builtin_catalog().unwrap())
        .unwrap();
    let err = tokenize_dataset(std::slice::from_ref(&other), &data, &out, None, 1, |_, _| {})
        .unwrap_err()
        .to_string();
    assert!(err.contains("another layout"), "{err}");
    let mixed = [registry, other];
    let err = tokenize_dataset(&mixed, &data, &dir.path().join("tokens-3"), None, 2, |_, _| {})
        .unwrap_err()
        .to_string();
    assert!(err.contains("differ in their layouts"), "{err}");
}
