//! Pictures of umgen scenes.
//!
//! [`scene_picture`] draws one frame as the bird's-eye view (map layers in distinct colours, agents as
//! boxes coloured by category with velocity arrows, the ego in red) above the camera view, with a label.
//! [`write_png`] and [`write_gif`] save pictures; `umgen viz` puts them together for a clip.

mod bev;
mod encode;
mod font;
mod image;

pub use bev::{BACKGROUND, EGO, agent_colour, draw_bev, layer_colour};
pub use encode::{Result, VizError, write_gif, write_png};
pub use font::text;
pub use image::Rgb;

use umgen_render::MapView;
use umgen_scene::{CameraImage, Frame, MapRaster};

/// Length and width of the ego box drawn in pictures (m): a mid-size car.
pub const EGO_SIZE: [f64; 2] = [4.6, 1.9];

/// One frame as a picture: the BEV (`view.size`, from `raster`) above the camera image (scaled to the
/// BEV's width), with `label` in the top-left corner.
pub fn scene_picture(
    view: &MapView,
    raster: Option<&MapRaster>,
    camera: Option<&CameraImage>,
    frame: &Frame,
    label: &str,
) -> Rgb {
    let bev = draw_bev(view, raster, &frame.agents, EGO_SIZE);
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
