//! Scene files (`docs/model.md`, "Scene files"): TOML in, a validated [`Scene`] out, and back to TOML.
//!
//! Every error names the key, or the row and column, at fault. The material table of a scene
//! lists the materials its legend uses, in legend order: that order is the default dictionary's.
//!
//! What the text controls is capped before anything is sized by it: the text's length
//! ([`MAX_SCENE_BYTES`]), the grid (4096) and sources (the geometry's limits), and the materials
//! and legend entries ([`MAX_MATERIALS`]); the map is built row by row, each row checked first.

use crate::geometry::Geometry;
use crate::material::{builtin_material, Material, MaterialTable, BUILTIN_MATERIALS};
use std::fmt::Write as _;
use thiserror::Error;

/// The longest scene text read: a 4096² map of four-byte symbols, with room for its materials.
pub const MAX_SCENE_BYTES: u64 = 80 << 20;
/// The most materials a scene may define, and the most legend entries.
pub const MAX_MATERIALS: usize = 1024;

/// A medium: geometry, materials and the material of every pixel.
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    pub geometry: Geometry,
    /// The materials the map uses, in legend order.
    pub table: MaterialTable,
    /// The one-character symbol of each table entry.
    pub symbols: Vec<char>,
    /// `N²` indices into `table`, row-major, row 0 at the top.
    pub assignment: Vec<u16>,
}

/// What is wrong with a scene file. `at` names the key (`geometry.grid`, `map.legend."x"`) or
/// the row and column (1-based).
#[derive(Debug, Error, Clone, PartialEq)]
pub enum SceneError {
    #[error("not valid TOML: {0}")]
    Toml(String),
    #[error("{at}: {message}")]
    Invalid { at: String, message: String },
}

fn invalid(at: impl Into<String>, message: impl Into<String>) -> SceneError {
    SceneError::Invalid {
        at: at.into(),
        message: message.into(),
    }
}

fn type_name(v: &toml::Value) -> &'static str {
    v.type_str()
}

/// A TOML number (integer or float) as f64.
fn number(v: &toml::Value, at: &str) -> Result<f64, SceneError> {
    match v {
        toml::Value::Float(f) => Ok(*f),
        toml::Value::Integer(i) => Ok(*i as f64),
        other => Err(invalid(
            at,
            format!("expected a number, got {}", type_name(other)),
        )),
    }
}

fn positive_int(v: &toml::Value, at: &str) -> Result<u32, SceneError> {
    match v {
        toml::Value::Integer(i) if *i > 0 && *i <= i64::from(u32::MAX) => Ok(*i as u32),
        toml::Value::Integer(i) => Err(invalid(
            at,
            format!("expected a positive whole number, got {i}"),
        )),
        other => Err(invalid(
            at,
            format!("expected a whole number, got {}", type_name(other)),
        )),
    }
}

fn check_keys(table: &toml::Table, allowed: &[&str], at: &str) -> Result<(), SceneError> {
    for key in table.keys() {
        if !allowed.contains(&key.as_str()) {
            let place = if at.is_empty() {
                key.clone()
            } else {
                format!("{at}.{key}")
            };
            return Err(invalid(
                place,
                format!("unknown key (expected one of: {})", allowed.join(", ")),
            ));
        }
    }
    Ok(())
}

fn parse_geometry(v: Option<&toml::Value>) -> Result<Geometry, SceneError> {
    let mut g = Geometry::default();
    let Some(v) = v else { return Ok(g) };
    let t = v
        .as_table()
        .ok_or_else(|| invalid("geometry", "expected a table"))?;
    check_keys(
        t,
        &["size_mm", "grid", "positions", "directions"],
        "geometry",
    )?;
    if let Some(v) = t.get("size_mm") {
        g.size_mm = number(v, "geometry.size_mm")?;
        if !(g.size_mm.is_finite() && g.size_mm > 0.0) {
            return Err(invalid(
                "geometry.size_mm",
                format!("must be a finite number > 0, got {}", g.size_mm),
            ));
        }
    }
    if let Some(v) = t.get("grid") {
        g.grid = positive_int(v, "geometry.grid")?;
        if !(g.grid.is_power_of_two() && g.grid <= 4096) {
            return Err(invalid(
                "geometry.grid",
                format!("must be a power of two up to 4096, got {}", g.grid),
            ));
        }
    }
    if let Some(v) = t.get("positions") {
        g.positions = positive_int(v, "geometry.positions")?;
        if !g.positions.is_multiple_of(4) {
            return Err(invalid(
                "geometry.positions",
                format!(
                    "must be divisible by 4 (the same count on each edge), got {}",
                    g.positions
                ),
            ));
        }
    }
    if let Some(v) = t.get("directions") {
        g.directions = positive_int(v, "geometry.directions")?;
    }
    g.validate()
        .map_err(|e| invalid("geometry", e.to_string()))?;
    Ok(g)
}

fn parse_material(name: &str, v: &toml::Value) -> Result<Material, SceneError> {
    let at = format!("materials.{name}");
    let t = v
        .as_table()
        .ok_or_else(|| invalid(&at, "expected a table { sigma_s, sigma_a, g }"))?;
    check_keys(t, &["sigma_s", "sigma_a", "g"], &at)?;
    let get = |key: &str| {
        t.get(key)
            .ok_or_else(|| invalid(&at, format!("missing key {key}")))
    };
    let sigma_s = number(get("sigma_s")?, &format!("{at}.sigma_s"))?;
    if !(sigma_s.is_finite() && sigma_s >= 0.0) {
        return Err(invalid(
            format!("{at}.sigma_s"),
            format!("must be a finite number >= 0, got {sigma_s}"),
        ));
    }
    let sigma_a = match get("sigma_a")? {
        toml::Value::String(s) if s == "inf" => f64::INFINITY,
        toml::Value::String(s) => {
            return Err(invalid(
                format!("{at}.sigma_a"),
                format!("must be a number >= 0 or \"inf\", got {s:?}"),
            ))
        }
        other => number(other, &format!("{at}.sigma_a"))?,
    };
    if sigma_a.is_nan() || sigma_a < 0.0 {
        return Err(invalid(
            format!("{at}.sigma_a"),
            format!("must be a number >= 0 or \"inf\", got {sigma_a}"),
        ));
    }
    let g = number(get("g")?, &format!("{at}.g"))?;
    if !(g.is_finite() && g.abs() <= 1.0) {
        return Err(invalid(
            format!("{at}.g"),
            format!("must lie in [-1, 1], got {g}"),
        ));
    }
    Ok(Material {
        sigma_s,
        sigma_a,
        g,
    })
}

impl Scene {
    /// Parses and validates a scene file's text.
    pub fn from_toml(text: &str) -> Result<Scene, SceneError> {
        if text.len() as u64 > MAX_SCENE_BYTES {
            return Err(invalid(
                "(file)",
                format!(
                    "{} bytes, more than the {MAX_SCENE_BYTES} a scene file may have",
                    text.len()
                ),
            ));
        }
        let doc: toml::Table = text
            .parse()
            .map_err(|e: toml::de::Error| SceneError::Toml(e.to_string()))?;
        check_keys(&doc, &["geometry", "materials", "map"], "")?;
        let geometry = parse_geometry(doc.get("geometry"))?;

        // User-defined materials, by name.
        let mut defined: Vec<(String, Material)> = Vec::new();
        if let Some(v) = doc.get("materials") {
            let t = v
                .as_table()
                .ok_or_else(|| invalid("materials", "expected a table"))?;
            if t.len() > MAX_MATERIALS {
                return Err(invalid(
                    "materials",
                    format!(
                        "{} materials, more than the {MAX_MATERIALS} a scene may define",
                        t.len()
                    ),
                ));
            }
            for (name, mv) in t {
                if builtin_material(name).is_some() {
                    return Err(invalid(
                        format!("materials.{name}"),
                        "redefines a built-in material; choose another name",
                    ));
                }
                defined.push((name.clone(), parse_material(name, mv)?));
            }
        }
        let lookup = |name: &str| {
            builtin_material(name)
                .or_else(|| defined.iter().find(|(n, _)| n == name).map(|(_, m)| *m))
        };

        let map = doc
            .get("map")
            .ok_or_else(|| invalid("map", "missing table [map] with legend and rows"))?;
        let map = map
            .as_table()
            .ok_or_else(|| invalid("map", "expected a table"))?;
        check_keys(map, &["legend", "rows"], "map")?;
        let legend = map
            .get("legend")
            .ok_or_else(|| invalid("map", "missing key legend"))?;
        let legend = legend
            .as_table()
            .ok_or_else(|| invalid("map.legend", "expected a table of symbol = material"))?;
        if legend.is_empty() {
            return Err(invalid("map.legend", "is empty"));
        }
        if legend.len() > MAX_MATERIALS {
            return Err(invalid(
                "map.legend",
                format!(
                    "{} symbols, more than the {MAX_MATERIALS} a legend may have",
                    legend.len()
                ),
            ));
        }
        let mut table = MaterialTable::default();
        let mut symbols = Vec::new();
        for (symbol, name) in legend {
            let at = format!("map.legend.{symbol:?}");
            let mut chars = symbol.chars();
            let ch = match (chars.next(), chars.next()) {
                (Some(c), None) => c,
                _ => return Err(invalid(at, "a symbol is exactly one character")),
            };
            let name = name
                .as_str()
                .ok_or_else(|| invalid(&at, "expected a material name (a string)"))?;
            let material = lookup(name).ok_or_else(|| {
                let mut known: Vec<&str> = BUILTIN_MATERIALS.iter().map(|(n, _)| *n).collect();
                known.extend(defined.iter().map(|(n, _)| n.as_str()));
                invalid(
                    &at,
                    format!("unknown material {name:?} (known: {})", known.join(", ")),
                )
            })?;
            if table.index_of(name).is_some() {
                return Err(invalid(
                    at,
                    format!("material {name:?} already has a symbol"),
                ));
            }
            table.push(name, material);
            symbols.push(ch);
        }

        let rows = map
            .get("rows")
            .ok_or_else(|| invalid("map", "missing key rows"))?;
        let rows = rows
            .as_array()
            .ok_or_else(|| invalid("map.rows", "expected an array of strings"))?;
        let n = geometry.grid as usize;
        if rows.len() != n {
            return Err(invalid(
                "map.rows",
                format!("expected {n} rows (grid = {n}), got {}", rows.len()),
            ));
        }
        // Grown row by row, each row checked first: the size follows what the text holds, not
        // what `grid` claims.
        let mut assignment = Vec::new();
        for (r, row) in rows.iter().enumerate() {
            let row = row
                .as_str()
                .ok_or_else(|| invalid(format!("map.rows, row {}", r + 1), "expected a string"))?;
            let len = row.chars().count();
            if len != n {
                return Err(invalid(
                    format!("map.rows, row {}", r + 1),
                    format!("expected {n} symbols, got {len}"),
                ));
            }
            assignment.reserve(n);
            for (c, ch) in row.chars().enumerate() {
                let index = symbols.iter().position(|&s| s == ch).ok_or_else(|| {
                    let known: String = symbols.iter().map(|s| format!("'{s}' ")).collect();
                    invalid(
                        format!("map.rows, row {}, column {}", r + 1, c + 1),
                        format!(
                            "unknown symbol '{ch}' (the legend has {})",
                            known.trim_end()
                        ),
                    )
                })?;
                assignment.push(index as u16);
            }
        }
        Ok(Scene {
            geometry,
            table,
            symbols,
            assignment,
        })
    }

    /// The scene as a scene file.
    pub fn to_toml(&self) -> String {
        let g = &self.geometry;
        let mut out = String::new();
        let _ = writeln!(out, "[geometry]");
        let _ = writeln!(out, "size_mm = {:?}", g.size_mm);
        let _ = writeln!(out, "grid = {}", g.grid);
        let _ = writeln!(out, "positions = {}", g.positions);
        let _ = writeln!(out, "directions = {}", g.directions);
        let custom: Vec<_> = self
            .table
            .materials
            .iter()
            .filter(|m| builtin_material(&m.name).is_none())
            .collect();
        if !custom.is_empty() {
            let _ = writeln!(out, "\n[materials]");
            for m in custom {
                let sigma_a = if m.material.is_opaque() {
                    "\"inf\"".to_string()
                } else {
                    format!("{:?}", m.material.sigma_a)
                };
                let _ = writeln!(
                    out,
                    "{} = {{ sigma_s = {:?}, sigma_a = {sigma_a}, g = {:?} }}",
                    m.name, m.material.sigma_s, m.material.g
                );
            }
        }
        let _ = writeln!(out, "\n[map]");
        let legend: Vec<String> = self
            .symbols
            .iter()
            .zip(&self.table.materials)
            .map(|(s, m)| format!("{:?} = {:?}", s.to_string(), m.name))
            .collect();
        let _ = writeln!(out, "legend = {{ {} }}", legend.join(", "));
        let _ = writeln!(out, "rows = [");
        let n = g.grid as usize;
        for row in self.assignment.chunks(n) {
            let text: String = row.iter().map(|&i| self.symbols[i as usize]).collect();
            let _ = writeln!(out, "  \"{text}\",");
        }
        let _ = writeln!(out, "]");
        out
    }

    /// The material of pixel `(row, col)`.
    pub fn material_at(&self, row: usize, col: usize) -> Material {
        let n = self.geometry.grid as usize;
        self.table.materials[self.assignment[row * n + col] as usize].material
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const EXAMPLE: &str = r##"
[geometry]
size_mm = 16.0
grid = 4
positions = 16
directions = 3

[materials]
fog = { sigma_s = 0.3, sigma_a = 0.02, g = 0.1 }

[map]
legend = { "." = "moderate", "#" = "opaque", "f" = "fog" }
rows = [
  "....",
  ".#f.",
  ".ff.",
  "....",
]
"##;

    fn err(text: &str) -> String {
        match Scene::from_toml(text) {
            Ok(_) => panic!("accepted a bad scene:\n{text}"),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn parses_the_model_example_and_round_trips() {
        let s = Scene::from_toml(EXAMPLE).unwrap();
        assert_eq!(s.geometry, Geometry::new(16.0, 4, 16, 3).unwrap());
        assert_eq!(s.table.len(), 3);
        assert_eq!(s.table.materials[2].name, "fog");
        assert!(s.material_at(1, 1).is_opaque());
        assert_eq!(s.material_at(2, 2).sigma_s, 0.3);
        let again = Scene::from_toml(&s.to_toml()).unwrap();
        assert_eq!(again, s);
    }

    #[test]
    fn missing_geometry_takes_the_defaults() {
        let rows: Vec<String> = (0..16).map(|_| format!("\"{}\"", ".".repeat(16))).collect();
        let text = format!(
            "[map]\nlegend = {{ \".\" = \"mild\" }}\nrows = [{}]\n",
            rows.join(",")
        );
        let s = Scene::from_toml(&text).unwrap();
        assert_eq!(s.geometry, Geometry::default());
    }

    fn with(from: &str, to: &str) -> String {
        assert!(EXAMPLE.contains(from), "{from}");
        EXAMPLE.replacen(from, to, 1)
    }

    #[test]
    fn each_bad_input_names_where_it_is() {
        let e = err(&with(".#f.", ".#x."));
        assert!(
            e.contains("row 2, column 3") && e.contains("unknown symbol 'x'"),
            "{e}"
        );
        let e = err(&with("  \"....\",\n]", "]"));
        assert!(
            e.contains("map.rows") && e.contains("expected 4 rows") && e.contains("got 3"),
            "{e}"
        );
        let e = err(&with(".ff.", ".ff.."));
        assert!(
            e.contains("row 3") && e.contains("expected 4 symbols, got 5"),
            "{e}"
        );
        let e = err(&with("grid = 4", "grid = 6"));
        assert!(
            e.contains("geometry.grid") && e.contains("power of two"),
            "{e}"
        );
        let e = err(&with("positions = 16", "positions = 18"));
        assert!(
            e.contains("geometry.positions") && e.contains("divisible by 4"),
            "{e}"
        );
        let e = err(&with("sigma_s = 0.3", "sigma_s = -0.3"));
        assert!(
            e.contains("materials.fog.sigma_s") && e.contains(">= 0"),
            "{e}"
        );
        let e = err(&with("sigma_s = 0.3", "sigma_s = nan"));
        assert!(e.contains("materials.fog.sigma_s"), "{e}");
        let e = err(&with("sigma_s = 0.3", "sigma_s = inf"));
        assert!(e.contains("materials.fog.sigma_s"), "{e}");
        let e = err(&with("sigma_a = 0.02", "sigma_a = \"lots\""));
        assert!(
            e.contains("materials.fog.sigma_a") && e.contains("\"inf\""),
            "{e}"
        );
        let e = err(&with("sigma_a = 0.02", "sigma_a = -1"));
        assert!(e.contains("materials.fog.sigma_a"), "{e}");
        let e = err(&with("g = 0.1", "g = 1.5"));
        assert!(
            e.contains("materials.fog.g") && e.contains("[-1, 1]"),
            "{e}"
        );
        let e = err(&with("\"f\" = \"fog\"", "\"f\" = \"fgo\""));
        assert!(
            e.contains("map.legend") && e.contains("unknown material \"fgo\""),
            "{e}"
        );
        let e = err(&with(
            "\"f\" = \"fog\"",
            "\"f\" = \"fog\", \"f\" = \"mild\"",
        ));
        assert!(
            e.contains("duplicate key `f`") && e.contains("line 12"),
            "{e}"
        );
        let e = err(&with(
            "\"#\" = \"opaque\"",
            "\"#\" = \"opaque\", \"o\" = \"opaque\"",
        ));
        assert!(
            e.contains("map.legend") && e.contains("already has a symbol"),
            "{e}"
        );
        let e = err(&with(
            "[materials]",
            "[materials]\nmild = { sigma_s = 1, sigma_a = 0, g = 0 }",
        ));
        assert!(
            e.contains("materials.mild") && e.contains("built-in"),
            "{e}"
        );
        let e = err(&with("directions = 3", "directions = 3\ncolour = 1"));
        assert!(
            e.contains("geometry.colour") && e.contains("unknown key"),
            "{e}"
        );
        let e = err(&with("sigma_a = 0.02, ", ""));
        assert!(
            e.contains("materials.fog") && e.contains("missing key sigma_a"),
            "{e}"
        );
    }

    #[test]
    fn sizes_the_text_controls_are_capped() {
        let mut many = String::from("[materials]\n");
        for i in 0..=MAX_MATERIALS {
            many.push_str(&format!("m{i} = {{ sigma_s = 1, sigma_a = 0, g = 0 }}\n"));
        }
        let e = err(&many);
        assert!(e.contains("materials") && e.contains("1024"), "{e}");
        let legend: Vec<String> = (0..=MAX_MATERIALS)
            .map(|i| {
                format!(
                    "\"{}\" = \"mild\"",
                    char::from_u32(0x4e00 + i as u32).unwrap()
                )
            })
            .collect();
        let e = err(&format!(
            "[map]\nlegend = {{ {} }}\nrows = []\n",
            legend.join(", ")
        ));
        assert!(e.contains("map.legend") && e.contains("1024"), "{e}");
        let e = err(&with("grid = 4", "grid = 8192"));
        assert!(e.contains("geometry.grid") && e.contains("4096"), "{e}");
        let e = err(&with("directions = 3", "directions = 4097"));
        assert!(e.contains("geometry") && e.contains("65536"), "{e}");
        // 4096 rows claimed by a grid, none of them valid: refused at the first row.
        let rows = vec!["\"\""; 4096].join(",");
        let text = format!(
            "[geometry]\ngrid = 4096\n[map]\nlegend = {{ \".\" = \"mild\" }}\nrows = [{rows}]\n"
        );
        let e = err(&text);
        assert!(
            e.contains("row 1") && e.contains("expected 4096 symbols"),
            "{e}"
        );
        let huge = " ".repeat(MAX_SCENE_BYTES as usize + 1);
        assert!(err(&huge).contains("more than the"));
    }

    #[test]
    fn opaque_from_the_string_inf() {
        let s = Scene::from_toml(&with("sigma_a = 0.02", "sigma_a = \"inf\"")).unwrap();
        assert!(s.material_at(1, 2).is_opaque());
        assert!(s.to_toml().contains("sigma_a = \"inf\""));
    }
}
