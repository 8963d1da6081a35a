//! The JSON sidecar of an observation file ([`Sidecar`]): its keys, checked one by one.

use super::*;

/// The JSON sidecar of an observation file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Sidecar {
    pub format: String,
    pub size_mm: f64,
    pub positions: u32,
    pub directions: u32,
    /// Photons launched per source (for captures: the effective sample size).
    pub photons_per_source: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub engine: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene_sha256: Option<String>,
    /// The scene file or built-in name the observation was rendered from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene: Option<String>,
    /// Photons that left the medium, over all sources.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub photons_exited: Option<u64>,
    /// Photons absorbed, over all sources.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub photons_absorbed: Option<u64>,
}

impl Sidecar {
    /// A sidecar for a render of `geometry` with `photons_per_source` photons.
    pub fn for_render(geometry: &Geometry, photons_per_source: u64) -> Self {
        Sidecar {
            format: FORMAT.into(),
            size_mm: geometry.size_mm,
            positions: geometry.positions,
            directions: geometry.directions,
            photons_per_source,
            seed: None,
            engine: None,
            scene_sha256: None,
            scene: None,
            photons_exited: None,
            photons_absorbed: None,
        }
    }

    /// Number of sources (and bins) `P·K`.
    pub fn sources(&self) -> usize {
        (self.positions as usize) * (self.directions as usize)
    }

    /// Parses and checks a sidecar's bytes key by key; `path` (the sidecar's) names it in errors.
    pub fn from_json(bytes: &[u8], path: &Path) -> Result<Sidecar, ObservationError> {
        let file = display(path);
        let value: serde_json::Value =
            serde_json::from_slice(bytes).map_err(|e| ObservationError::SidecarJson {
                file: file.clone(),
                detail: e.to_string(),
            })?;
        let serde_json::Value::Object(object) = value else {
            return Err(ObservationError::SidecarJson {
                file,
                detail: format!("found {}", json_type(&value)),
            });
        };
        let key_error = |key: &'static str, expected: &'static str, detail: String| {
            ObservationError::SidecarKey {
                file: file.clone(),
                key,
                expected,
                detail,
            }
        };
        // A key's value as `T`; `None` when absent (or null).
        fn field<T: DeserializeOwned>(
            object: &serde_json::Map<String, serde_json::Value>,
            key: &'static str,
            expected: &'static str,
            error: &dyn Fn(&'static str, &'static str, String) -> ObservationError,
        ) -> Result<Option<T>, ObservationError> {
            match object.get(key) {
                None | Some(serde_json::Value::Null) => Ok(None),
                Some(v) => T::deserialize(v)
                    .map(Some)
                    .map_err(|_| error(key, expected, format!(", got {}", short(v)))),
            }
        }
        fn required<T>(
            v: Option<T>,
            key: &'static str,
            expected: &'static str,
            error: &dyn Fn(&'static str, &'static str, String) -> ObservationError,
        ) -> Result<T, ObservationError> {
            v.ok_or_else(|| error(key, expected, ", but it is missing".into()))
        }
        let e = &key_error;
        let format: String = required(
            field(&object, "format", "a string", e)?,
            "format",
            "a string",
            e,
        )?;
        if format != FORMAT {
            return Err(e(
                "format",
                "\"scatterfarm-observation/1\"",
                format!(", got {format:?}"),
            ));
        }
        const SIZE: &str = "a finite number of mm > 0";
        let size_mm: f64 = required(field(&object, "size_mm", SIZE, e)?, "size_mm", SIZE, e)?;
        if !(size_mm.is_finite() && size_mm > 0.0) {
            return Err(e("size_mm", SIZE, format!(", got {size_mm}")));
        }
        const POSITIONS: &str = "a whole number > 0 divisible by 4";
        let positions: u32 = required(
            field(&object, "positions", POSITIONS, e)?,
            "positions",
            POSITIONS,
            e,
        )?;
        if positions == 0 || !positions.is_multiple_of(4) {
            return Err(e("positions", POSITIONS, format!(", got {positions}")));
        }
        const DIRECTIONS: &str = "a whole number >= 1";
        let directions: u32 = required(
            field(&object, "directions", DIRECTIONS, e)?,
            "directions",
            DIRECTIONS,
            e,
        )?;
        if directions == 0 {
            return Err(e("directions", DIRECTIONS, format!(", got {directions}")));
        }
        let geometry = Geometry {
            size_mm,
            grid: 1,
            positions,
            directions,
        };
        if let Err(g) = geometry.validate() {
            return Err(e(
                "directions",
                "positions × directions within the geometry's limit",
                format!(": {g}"),
            ));
        }
        const PHOTONS: &str = "a whole number >= 1";
        let photons_per_source: u64 = required(
            field(&object, "photons_per_source", PHOTONS, e)?,
            "photons_per_source",
            PHOTONS,
            e,
        )?;
        if photons_per_source == 0 {
            return Err(e("photons_per_source", PHOTONS, ", got 0".into()));
        }
        const WHOLE: &str = "a whole number >= 0";
        const TEXT: &str = "a string";
        Ok(Sidecar {
            format,
            size_mm,
            positions,
            directions,
            photons_per_source,
            seed: field(&object, "seed", WHOLE, e)?,
            engine: field(&object, "engine", TEXT, e)?,
            scene_sha256: field(&object, "scene_sha256", TEXT, e)?,
            scene: field(&object, "scene", TEXT, e)?,
            photons_exited: field(&object, "photons_exited", WHOLE, e)?,
            photons_absorbed: field(&object, "photons_absorbed", WHOLE, e)?,
        })
    }
}

fn json_type(v: &serde_json::Value) -> &'static str {
    match v {
        serde_json::Value::Null => "null",
        serde_json::Value::Bool(_) => "a boolean",
        serde_json::Value::Number(_) => "a number",
        serde_json::Value::String(_) => "a string",
        serde_json::Value::Array(_) => "an array",
        serde_json::Value::Object(_) => "an object",
    }
}

/// A JSON value for an error message: numbers and short strings as they are, else its type.
fn short(v: &serde_json::Value) -> String {
    match v {
        serde_json::Value::Number(n) => n.to_string(),
        serde_json::Value::Bool(b) => b.to_string(),
        serde_json::Value::String(s) if s.len() <= 64 => format!("{s:?}"),
        other => json_type(other).to_string(),
    }
}
