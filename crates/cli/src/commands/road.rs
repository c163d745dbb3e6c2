//! `umgen generate --entering-on-road`: the road rule ([`RoadRule`]) against each frame's own map. A
//! scene's map codes are decoded by the bundle's map modality only in frames where a vehicle enters, and
//! its drivable layers (lanes, intersections, lane connectors) are read at the entering vehicles' centres.

use super::frame_map::FrameMap;
use anyhow::Context;
use umgen::Bundle;
use umgen::generate::{Area, RoadCount, RoadRule, TokenGroups};
use umgen::modality::ModalityRegistry;
use umgen::scene::MapRaster;
use umgen_render::MapView;

/// The rule and what reads a frame's map.
pub(super) struct RoadCheck<'a> {
    rule: RoadRule,
    map: FrameMap<'a>,
    channels: Vec<usize>,
}

/// One frame's decoded map, as the rule reads it.
struct OwnMap<'v> {
    view: &'v MapView,
    channels: &'v [usize],
    raster: MapRaster,
}

impl Area for OwnMap<'_> {
    fn covers(&self, p: [f64; 2]) -> Option<bool> {
        self.view.covers(&self.raster, self.channels, p)
    }
}

impl<'a> RoadCheck<'a> {
    /// The rule over the agent slots `groups` (vehicle category id `vehicle`) with the bundle's map
    /// modality; an error names what the model lacks for it.
    pub(super) fn new(
        bundle: &Bundle,
        registry: &'a ModalityRegistry,
        groups: &TokenGroups,
        vehicle: u32,
    ) -> anyhow::Result<Self> {
        let map = FrameMap::new(
            bundle,
            registry,
            "--entering-on-road",
            "reads the frame's own map",
        )?;
        let channels = map.view.drivable_channels();
        anyhow::ensure!(
            !channels.is_empty(),
            "--entering-on-road: the map modality `{}` draws none of the drivable layers (lane, \
             intersection, lane_connector); its layers are {:?}",
            map.modality,
            map.view.layers.iter().map(|l| l.name()).collect::<Vec<_>>()
        );
        Ok(Self {
            rule: RoadRule::new(groups.clone(), vehicle)?,
            map,
            channels,
        })
    }

    /// Applies the rule to each scene's new frame `frames[s]`, against the newest frame of `history[s]`
    /// (scenes without one, made from nothing, have no entering vehicles); `placed` are the positions the
    /// caller set, whose groups are never tested.
    pub(super) fn apply(
        &self,
        frames: &mut [Vec<u32>],
        history: &[Vec<Vec<u32>>],
        placed: &[usize],
    ) -> anyhow::Result<RoadCount> {
        let mut count = RoadCount::default();
        for (s, (frame, h)) in frames.iter_mut().zip(history).enumerate() {
            let Some(before) = h.last() else {
                continue;
            };
            let entering = self.rule.entering(frame, before, placed);
            if entering.is_empty() {
                continue;
            }
            let raster = self.map.decode(frame).with_context(|| format!("scene {s}"))?;
            let area = OwnMap {
                view: &self.map.view,
                channels: &self.channels,
                raster,
            };
            count += self.rule.apply(frame, &entering, &area);
        }
        Ok(count)
    }
}
