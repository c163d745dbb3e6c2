//! Where the host waits around side-stream work ([`SideSync`], `train.kernels.side_sync`).

use serde::{Deserialize, Serialize};

/// A kernel family that runs on side streams (`stream = "side"`), as [`SideSync`] names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SideFamily {
    /// The cross-entropy's kernels.
    CrossEntropy,
    /// The layer norm's kernels.
    LayerNorm,
    /// The TAR's attention over time.
    AttentionOverTime,
    /// The flash2 attention kernels.
    Attention,
    /// cuBLAS's products.
    Cublas,
}

impl SideFamily {
    const ALL: [SideFamily; 5] = [
        SideFamily::CrossEntropy,
        SideFamily::LayerNorm,
        SideFamily::AttentionOverTime,
        SideFamily::Attention,
        SideFamily::Cublas,
    ];

    /// Its name in configs and logs.
    pub fn name(self) -> &'static str {
        match self {
            SideFamily::CrossEntropy => "cross-entropy",
            SideFamily::LayerNorm => "layer-norm",
            SideFamily::AttentionOverTime => "attention-over-time",
            SideFamily::Attention => "attention",
            SideFamily::Cublas => "cublas",
        }
    }
}

/// Where the host waits around a family's side-stream work: `before` (for cubecl's stream to drain before
/// the work is queued), `after` (for the side stream to finish it before cubecl's stream queues more),
/// for every family or only one. Written `MODE` or `MODE:FAMILY`, MODE one of `before`, `after`, `both`,
/// `none`. The default, `after:cross-entropy`, is what the side-stream protocol needs: without that wait,
/// one-step runs from one seed gave a wrong gradient in 1 of 15 runs of `small-bundled` and 13 of 15 with
/// burn's layer norm on an H100, with it none of 30 (docs/decisions/004-cuda-kernels-on-cubecl-stream.md).
/// Other values are for finding ordering faults (`umgen-kernel-bench repro`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct SideSync {
    before: bool,
    after: bool,
    only: Option<SideFamily>,
}

impl SideSync {
    /// `after:cross-entropy`.
    pub const DEFAULT: Self = Self {
        before: false,
        after: true,
        only: Some(SideFamily::CrossEntropy),
    };

    /// The host's waits around `family`'s work: (before, after).
    pub fn waits(&self, family: SideFamily) -> (bool, bool) {
        match self.only {
            Some(f) if f != family => (false, false),
            _ => (self.before, self.after),
        }
    }
}

impl Default for SideSync {
    fn default() -> Self {
        Self::DEFAULT
    }
}

impl TryFrom<String> for SideSync {
    type Error = String;

    fn try_from(s: String) -> Result<Self, String> {
        let (mode, family) = match s.split_once(':') {
            Some((m, f)) => (m, Some(f)),
            None => (s.as_str(), None),
        };
        let (before, after) = match mode {
            "before" => (true, false),
            "after" => (false, true),
            "both" => (true, true),
            "none" => (false, false),
            other => {
                return Err(format!(
                    "side sync `{other}`: expected before, after, both or none"
                ));
            }
        };
        let only = match family {
            None => None,
            Some(f) => Some(
                SideFamily::ALL
                    .into_iter()
                    .find(|x| x.name() == f)
                    .ok_or_else(|| {
                        let names: Vec<&str> = SideFamily::ALL.iter().map(|x| x.name()).collect();
                        format!("side sync family `{f}`: expected one of {}", names.join(", "))
                    })?,
            ),
        };
        Ok(Self { before, after, only })
    }
}

impl From<SideSync> for String {
    fn from(s: SideSync) -> String {
        let mode = match (s.before, s.after) {
            (true, false) => "before",
            (false, true) => "after",
            (true, true) => "both",
            (false, false) => "none",
        };
        match s.only {
            Some(f) => format!("{mode}:{}", f.name()),
            None => mode.to_string(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn side_sync_reads_and_writes_its_form() {
        for text in [
            "after:cross-entropy",
            "both",
            "before:cublas",
            "none",
            "after:layer-norm",
        ] {
            let s: SideSync = serde_json::from_str(&format!("\"{text}\"")).expect(text);
            assert_eq!(String::from(s), text);
        }
        assert_eq!(SideSync::DEFAULT.waits(SideFamily::CrossEntropy), (false, true));
        assert_eq!(SideSync::DEFAULT.waits(SideFamily::Cublas), (false, false));
        let both = SideSync::try_from("both".to_string()).expect("both");
        assert_eq!(both.waits(SideFamily::Attention), (true, true));
        let e = SideSync::try_from("after:norm".to_string()).expect_err("no family `norm`");
        assert!(e.contains("norm") && e.contains("layer-norm"), "{e}");
        assert!(SideSync::try_from("sometimes".to_string()).is_err());
    }
}
