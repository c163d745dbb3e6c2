//! A frame's own map: the bundle's map modality decoding the map codes of a token row into a raster of
//! its view, for the generation options that read it (`--entering-on-road`, `--map-memory`).

use anyhow::Context;
use std::ops::Range;
use umgen::Bundle;
use umgen::modality::{Modality, ModalityRegistry};
use umgen::scene::{Frame, MapRaster};
use umgen_render::MapView;

/// The map modality, its segment and its view.
pub(super) struct FrameMap<'a> {
    pub map: &'a dyn Modality,
    /// The modality's name.
    pub modality: String,
    /// The segment's index in the layout, and its content positions in a row.
    pub segment: usize,
    pub codes: Range<usize>,
    pub view: MapView,
}

impl<'a> FrameMap<'a> {
    /// The bundle's map modality for the generation option `option`, which needs it for `purpose`; an
    /// error names the option and what the model lacks.
    pub(super) fn new(
        bundle: &Bundle,
        registry: &'a ModalityRegistry,
        option: &str,
        purpose: &str,
    ) -> anyhow::Result<Self> {
        let (map, seg) = super::agents::modality_of_kind(registry, umgen::modality_map::KIND)?
            .with_context(|| format!("{option} {purpose}, and this model has no map modality"))?;
        let segment = registry
            .layout()?
            .segments()
            .iter()
            .position(|s| s.modality == seg.modality)
            .context("the map modality has no segment in the layout")?;
        let view = super::scenes::map_view(bundle)?
            .with_context(|| format!("{option}: the bundle's config has no map settings"))?;
        Ok(Self {
            map,
            modality: seg.modality.clone(),
            segment,
            codes: seg.content(),
            view,
        })
    }

    /// The raster that the map codes of `row` decode to.
    pub(super) fn decode(&self, row: &[u32]) -> anyhow::Result<MapRaster> {
        let codes = row.get(self.codes.clone()).with_context(|| {
            format!(
                "a frame of {} tokens has no map codes at {:?}",
                row.len(),
                self.codes
            )
        })?;
        let mut f = Frame::default();
        self.map
            .detokenize(codes, &mut f)
            .context("decoding the frame's map codes")?;
        let raster = f.map.context("the frame's map codes decode to no raster")?;
        anyhow::ensure!(
            [raster.height, raster.width] == self.view.size,
            "the map codes decode to a {}×{} raster, but the map modality's view is {:?}",
            raster.height,
            raster.width,
            self.view.size
        );
        Ok(raster)
    }
}
