//! Vehicle and person types: category and box size per SUMO type id.

use super::xml::{Item, XmlStream};
use crate::error::Result;
use std::collections::HashMap;
use std::path::Path;
use umgen_scene::AgentCategory;

/// What a SUMO type id means for umgen.
#[derive(Debug, Clone, PartialEq)]
pub struct TypeInfo {
    /// SUMO vehicle class.
    pub class: String,
    /// Category, or `None` for classes umgen does not model (rail, ships).
    pub category: Option<AgentCategory>,
    /// Length (m).
    pub length: f64,
    /// Width (m).
    pub width: f64,
    /// Height (m).
    pub height: f64,
}

/// SUMO's default length, width and height per vehicle class (SUMO's vehicle type parameter defaults),
/// used when a type does not set them. Unknown classes use the passenger car's.
pub fn class_defaults(class: &str) -> (f64, f64, f64) {
    match class {
        "pedestrian" => (0.215, 0.478, 1.719),
        "bicycle" => (1.6, 0.65, 1.7),
        "moped" => (2.1, 0.8, 1.7),
        "motorcycle" => (2.2, 0.9, 1.5),
        "truck" => (7.1, 2.4, 2.4),
        "trailer" => (16.5, 2.55, 4.0),
        "bus" => (12.0, 2.5, 3.4),
        "coach" => (14.0, 2.6, 4.0),
        "delivery" | "emergency" => (6.5, 2.16, 2.86),
        "tram" => (22.0, 2.4, 3.2),
        "rail_urban" | "rail" | "rail_electric" | "rail_fast" | "subway" => (36.5, 3.0, 3.6),
        _ => (5.0, 1.8, 1.5),
    }
}

/// The umgen category of a SUMO class.
pub fn class_category(class: &str) -> Option<AgentCategory> {
    match class {
        "pedestrian" => Some(AgentCategory::Pedestrian),
        "bicycle" => Some(AgentCategory::Cyclist),
        "tram" | "rail_urban" | "rail" | "rail_electric" | "rail_fast" | "subway" | "ship" | "aircraft"
        | "cable_car" => None,
        _ => Some(AgentCategory::Vehicle),
    }
}

fn info(class: &str, length: Option<f64>, width: Option<f64>, height: Option<f64>) -> TypeInfo {
    let (l, w, h) = class_defaults(class);
    TypeInfo {
        class: class.into(),
        category: class_category(class),
        length: length.unwrap_or(l),
        width: width.unwrap_or(w),
        height: height.unwrap_or(h),
    }
}

/// Type ids and what they mean: SUMO's built-in default types, then every `<vType>` in `files`.
#[derive(Debug, Clone)]
pub struct TypeTable {
    types: HashMap<String, TypeInfo>,
}

impl TypeTable {
    /// SUMO's built-in types.
    pub fn builtin() -> Self {
        let types = [
            ("DEFAULT_VEHTYPE", "passenger"),
            ("DEFAULT_PEDTYPE", "pedestrian"),
            ("DEFAULT_BIKETYPE", "bicycle"),
            ("DEFAULT_TAXITYPE", "taxi"),
            ("DEFAULT_RAILTYPE", "rail"),
            ("DEFAULT_CONTAINERTYPE", "ignoring"),
        ]
        .into_iter()
        .map(|(id, class)| (id.to_string(), info(class, None, None, None)))
        .collect();
        Self { types }
    }

    /// The built-in types plus the `<vType>` definitions of route or additional files.
    pub fn load(files: &[impl AsRef<Path>]) -> Result<Self> {
        let mut table = Self::builtin();
        for f in files {
            let mut xml = XmlStream::open(f.as_ref())?;
            while let Some(item) = xml.next()? {
                let Item::Open(el) = item else { continue };
                if el.name != "vType" {
                    continue;
                }
                let id = el.req("id", &xml)?.to_string();
                // SUMO's own default class for a type without vClass is passenger.
                let class = el.get("vClass").unwrap_or("passenger").to_string();
                let dims = [
                    el.opt_num("length", &xml)?,
                    el.opt_num("width", &xml)?,
                    el.opt_num("height", &xml)?,
                ];
                if dims.iter().flatten().any(|&v| v <= 0.0) {
                    return Err(xml.error(&el, format!("vType `{id}`: sizes must be positive")));
                }
                table.types.insert(id, info(&class, dims[0], dims[1], dims[2]));
            }
        }
        Ok(table)
    }

    /// What a type id means.
    pub fn get(&self, id: &str) -> Option<&TypeInfo> {
        self.types.get(id)
    }
}
