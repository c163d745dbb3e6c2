//! The map part of `umgen eval` within the context's view: of a generated frame's window, the ground that
//! some context frame's window showed. There the real road network was in the model's input, and the map
//! its codes draw and the vehicles on it can be held to the real network; beyond it, where the generated
//! ego has driven into ground the context never showed, the model's roads are its own invention.

use umgen::scene::{AgentCategory, Frame, MapRaster, Pose2};
use umgen::tokenizer_vq::IouCounter;
use umgen_render::MapView;

/// The context frames' windows: their ego poses and the windows' half side (m).
pub(super) struct ContextView {
    poses: Vec<Pose2>,
    half: f64,
}

impl ContextView {
    /// The windows of `frames` (the context, at its real poses) in `view`'s square.
    pub(super) fn new(frames: &[Frame], view: &MapView) -> Self {
        Self {
            poses: frames.iter().map(|f| f.ego.pose2()).collect(),
            half: view.extent_m / 2.0,
        }
    }

    /// Whether some context window holds the global point `g`.
    fn holds(&self, g: [f64; 2]) -> bool {
        self.poses.iter().any(|c| {
            let [x, y] = c.to_local(g);
            x.abs() <= self.half && y.abs() <= self.half
        })
    }

    /// Per cell of `view` around `pose` (rows, then columns), whether some context window holds its centre.
    fn cells(&self, view: &MapView, pose: &Pose2) -> Vec<bool> {
        let [h, w] = view.size;
        (0..h * w)
            .map(|i| self.holds(pose.to_parent(view.pixel_to_ego(i / w, i % w))))
            .collect()
    }
}

/// Frames pooled within the context's view.
#[derive(Default)]
pub(super) struct Seen {
    iou: IouCounter,
    cells: usize,
    seen: usize,
    /// Vehicles whose centre lies within the view, and those of them on no drivable cell of the real map.
    vehicles: usize,
    vehicles_off: usize,
    /// Vehicles entering a frame (absent from the one before) inside the raster; those of them within
    /// the view, and of those, the ones off the real map's drivable cells.
    entering: usize,
    entering_inside: usize,
    entering_inside_off: usize,
}

impl Seen {
    /// Adds a frame at `pose` with its agents: `decoded` and `rendered` are the map its codes decode to and
    /// the real network rendered at `pose` (both in `view`'s raster, read as cells set above 127), and
    /// `channels` the drivable layers' channels. Cells outside the context's view count in neither map.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn add(
        &mut self,
        context: &ContextView,
        view: &MapView,
        pose: &Pose2,
        decoded: &[f32],
        rendered_cells: &[f32],
        rendered: &MapRaster,
        channels: &[usize],
        frame: &Frame,
        before: Option<&Frame>,
    ) {
        let seen = context.cells(view, pose);
        let plane = seen.len().max(1);
        let within = |v: &[f32]| -> Vec<f32> {
            v.iter()
                .enumerate()
                .map(|(i, &x)| if seen[i % plane] { x } else { 0.0 })
                .collect()
        };
        let [h, w] = view.size;
        let layers = decoded.len() / plane;
        self.iou
            .add(layers, [h, w], &within(decoded), &within(rendered_cells));
        self.cells += plane;
        self.seen += seen.iter().filter(|&&s| s).count();
        for a in frame
            .agents
            .iter()
            .filter(|a| a.category == AgentCategory::Vehicle)
        {
            let p = [a.x, a.y];
            let Some(on) = view.covers(rendered, channels, p) else {
                continue;
            };
            let inside = context.holds(pose.to_parent(p));
            if before.is_some_and(|b| !b.agents.iter().any(|o| o.track_id == a.track_id)) {
                self.entering += 1;
                self.entering_inside += usize::from(inside);
                self.entering_inside_off += usize::from(inside && !on);
            }
            if inside {
                self.vehicles += 1;
                self.vehicles_off += usize::from(!on);
            }
        }
    }

    /// `{"share", "iou": [per layer], "vehicles", "vehicles_off_road", "entering_inside",
    /// "entering_off_road"}`: the share of the windows' cells within the context's view, the IoU there,
    /// the vehicles there and the share of them off the real network's drivable cells; of the vehicles
    /// entering inside the raster, the share within the view, and of those the share off the real road.
    pub(super) fn json(&self) -> serde_json::Value {
        let share = |n: usize, of: usize| (of > 0).then(|| n as f64 / of as f64);
        serde_json::json!({
            "share": share(self.seen, self.cells),
            "iou": self.iou.iou(),
            "vehicles": self.vehicles,
            "vehicles_off_road": share(self.vehicles_off, self.vehicles),
            "entering_inside": share(self.entering_inside, self.entering),
            "entering_off_road": share(self.entering_inside_off, self.entering_inside),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use umgen::scene::{Agent, EgoPose, MapLayer, RoadNetwork};
    use umgen_eval::collision::bev_box;

    fn frame_at(x: f64, agents: Vec<Agent>) -> Frame {
        Frame {
            ego: EgoPose {
                x,
                ..EgoPose::default()
            },
            agents,
            ..Frame::default()
        }
    }

    /// A road along global x; the context saw the window around x = 0, the generated frame stands 100 m
    /// further on: the 28 m of its window behind it lie in the context's view, the rest beyond it.
    #[test]
    fn only_the_ground_the_context_showed_counts() {
        let network = RoadNetwork {
            lanes: vec![vec![[-300.0, -2.0], [300.0, -2.0], [300.0, 2.0], [-300.0, 2.0]]],
            ..RoadNetwork::default()
        };
        let view = MapView {
            extent_m: 128.0,
            size: [64, 64],
            layers: vec![MapLayer::Lane],
        };
        let context = ContextView::new(&[frame_at(0.0, Vec::new())], &view);
        let car = |id: u64, x: f64, y: f64| Agent {
            track_id: id,
            category: AgentCategory::Vehicle,
            ..bev_box(x, y, 0.0, 4.0, 2.0)
        };
        // Behind the ego, within the view: one on the road, one beside it. Ahead, beyond it: beside the
        // road, not counted.
        let frame = frame_at(
            100.0,
            vec![car(1, -50.0, 0.0), car(2, -50.0, 20.0), car(3, 30.0, 20.0)],
        );
        let pose = frame.ego.pose2();
        let rendered = view.render(&network, &pose);
        let cells: Vec<f32> = rendered.data.iter().map(|&v| f32::from(v > 127)).collect();
        // The decoded map draws the road ahead (rows 0..32) only: it misses the real road behind.
        let decoded: Vec<f32> = cells
            .iter()
            .enumerate()
            .map(|(i, &v)| if i / 64 < 32 { v } else { 0.0 })
            .collect();
        let mut seen = Seen::default();
        let channels = view.drivable_channels();
        // The two behind the ego enter; the one ahead was there before.
        let before = frame_at(99.0, vec![car(3, 30.0, 20.0)]);
        seen.add(
            &context,
            &view,
            &pose,
            &decoded,
            &cells,
            &rendered,
            &channels,
            &frame,
            Some(&before),
        );
        let j = seen.json();
        // Rows whose centre lies 36 m or more behind the ego (x ≤ 64 − 100): 14 of 64.
        assert_eq!(j["share"].as_f64(), Some(14.0 / 64.0), "{j}");
        assert_eq!(
            j["iou"][0].as_f64(),
            Some(0.0),
            "the road behind is all the view holds: {j}"
        );
        assert_eq!(
            (j["vehicles"].as_u64(), j["vehicles_off_road"].as_f64()),
            (Some(2), Some(0.5))
        );
        let entering = (j["entering_inside"].as_f64(), j["entering_off_road"].as_f64());
        assert_eq!(entering, (Some(1.0), Some(0.5)), "{j}");
        // The whole window, with the decoded map right: IoU 1 within the view.
        let mut whole = Seen::default();
        whole.add(
            &context, &view, &pose, &cells, &cells, &rendered, &channels, &frame, None,
        );
        assert_eq!(whole.json()["iou"][0].as_f64(), Some(1.0));
        assert!(
            whole.json()["entering_inside"].is_null(),
            "no frame before, no entries"
        );
        // Only the one ahead enters: none within the view.
        let mut ahead = Seen::default();
        let behind = frame_at(99.0, vec![car(1, -50.0, 0.0), car(2, -50.0, 20.0)]);
        ahead.add(
            &context,
            &view,
            &pose,
            &cells,
            &cells,
            &rendered,
            &channels,
            &frame,
            Some(&behind),
        );
        let j = ahead.json();
        let entering = (j["entering_inside"].as_f64(), j["entering_off_road"].as_f64());
        assert_eq!(entering, (Some(0.0), None), "{j}");
    }
}
