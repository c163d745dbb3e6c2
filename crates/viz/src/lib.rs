//! Pictures of umgen scenes.
//!
//! [`scene_picture`] draws one frame as the bird's-eye view (map layers in distinct colours, agents as
//! boxes coloured by category with velocity arrows, the ego in red, and the [`Mark`]s that modalities add
//! for their own content) above the camera view, with a label.
//! [`write_png`] and [`write_gif`] save pictures; `umgen viz` puts them together for a clip.

mod bev;
mod encode;
mod font;
mod image;

pub use bev::{BACKGROUND, EGO, agent_colour, draw_bev, draw_marks, layer_colour};
pub use encode::{Result, VizError, write_gif, write_png};
pub use font::text;
pub use image::Rgb;

use umgen_modality::Mark;
use umgen_render::MapView;
use umgen_scene::{CameraImage, Frame, MapRaster};

/// Length and width of the ego box drawn in pictures (m): a mid-size car.
pub const EGO_SIZE: [f64; 2] = [4.6, 1.9];

/// One frame as a picture: the BEV (`view.size`, from `raster`, with `marks` on top) above the camera image
/// (scaled to the BEV's width), with `label` in the top-left corner.
pub fn scene_picture(
    view: &MapView,
    raster: Option<&MapRaster>,
    camera: Option<&CameraImage>,
    frame: &Frame,
    marks: &[Mark],
    label: &str,
) -> Rgb {
    let mut bev = draw_bev(view, raster, &frame.agents, EGO_SIZE);
    draw_marks(&mut bev, view, marks);
    let cam = camera.map(|c| Rgb::from_camera(c, bev.width));
    let height = bev.height + cam.as_ref().map_or(0, |c| c.height);
    let mut out = Rgb::filled(bev.width, height, BACKGROUND);
    out.blit(&bev, 0, 0);
    if let Some(cam) = &cam {
        out.blit(cam, bev.height, 0);
    }
    text(&mut out, 4, 4, 2, label, [250, 250, 250]);
    out
}
