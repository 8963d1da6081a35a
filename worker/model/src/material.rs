//! Materials: `(σs, σa, g)` triples, the two special ones (transmissive, opaque), the paper's
//! built-in dictionary, and the material tables that renders index into.

use serde::{Deserialize, Serialize};
use thiserror::Error;

/// One homogeneous material. Coefficients are in mm⁻¹; `sigma_a = +∞` means opaque.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Material {
    /// Scattering coefficient σs (mm⁻¹), finite and ≥ 0.
    pub sigma_s: f64,
    /// Absorption coefficient σa (mm⁻¹), ≥ 0; `f64::INFINITY` makes the material opaque.
    #[serde(with = "sigma_a_serde")]
    pub sigma_a: f64,
    /// Henyey–Greenstein parameter g ∈ [−1, 1].
    pub g: f64,
}

/// Why a material is not a valid one.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum MaterialError {
    #[error("sigma_s must be a finite number >= 0, got {0}")]
    SigmaS(f64),
    #[error("sigma_a must be a number >= 0 or \"inf\", got {0}")]
    SigmaA(f64),
    #[error("g must lie in [-1, 1], got {0}")]
    G(f64),
}

impl Material {
    /// Light passes straight through.
    pub const TRANSMISSIVE: Material = Material {
        sigma_s: 0.0,
        sigma_a: 0.0,
        g: 0.0,
    };
    /// Absorbs every photon that enters.
    pub const OPAQUE: Material = Material {
        sigma_s: 0.0,
        sigma_a: f64::INFINITY,
        g: 0.0,
    };

    /// A validated material.
    pub fn new(sigma_s: f64, sigma_a: f64, g: f64) -> Result<Self, MaterialError> {
        let m = Material {
            sigma_s,
            sigma_a,
            g,
        };
        m.validate()?;
        Ok(m)
    }

    /// Checks the ranges of `docs/model.md`: σs finite ≥ 0, σa ≥ 0 or +∞, |g| ≤ 1.
    pub fn validate(&self) -> Result<(), MaterialError> {
        if !(self.sigma_s.is_finite() && self.sigma_s >= 0.0) {
            return Err(MaterialError::SigmaS(self.sigma_s));
        }
        if self.sigma_a.is_nan() || self.sigma_a < 0.0 || self.sigma_a == f64::NEG_INFINITY {
            return Err(MaterialError::SigmaA(self.sigma_a));
        }
        if !(self.g.is_finite() && self.g.abs() <= 1.0) {
            return Err(MaterialError::G(self.g));
        }
        Ok(())
    }

    /// Absorbs every photon that enters it.
    pub fn is_opaque(&self) -> bool {
        self.sigma_a == f64::INFINITY
    }

    /// Extinction coefficient σt = σs + σa (infinite for opaque).
    pub fn sigma_t(&self) -> f64 {
        self.sigma_s + self.sigma_a
    }

    /// σa as used by the paper's error measure: opaque counts as 1 mm⁻¹ (`docs/model.md`, "Reporting").
    pub fn sigma_a_for_error(&self) -> f64 {
        if self.is_opaque() {
            1.0
        } else {
            self.sigma_a
        }
    }
}

/// The paper's Table 1, by name, in the order the paper lists them.
pub const BUILTIN_MATERIALS: [(&str, Material); 6] = [
    ("transmissive", Material::TRANSMISSIVE),
    ("opaque", Material::OPAQUE),
    (
        "moderate",
        Material {
            sigma_s: 0.60,
            sigma_a: 0.01,
            g: 0.75,
        },
    ),
    (
        "mild",
        Material {
            sigma_s: 0.50,
            sigma_a: 0.03,
            g: 0.60,
        },
    ),
    (
        "uniform",
        Material {
            sigma_s: 0.80,
            sigma_a: 0.01,
            g: 0.0,
        },
    ),
    (
        "back",
        Material {
            sigma_s: 0.60,
            sigma_a: 0.10,
            g: -0.50,
        },
    ),
];

/// A built-in material by name.
pub fn builtin_material(name: &str) -> Option<Material> {
    BUILTIN_MATERIALS
        .iter()
        .find(|(n, _)| *n == name)
        .map(|(_, m)| *m)
}

/// A material with the name users and files know it by.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NamedMaterial {
    pub name: String,
    #[serde(flatten)]
    pub material: Material,
}

/// The ordered list of materials a render's assignment indexes into (`u16` indices).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MaterialTable {
    pub materials: Vec<NamedMaterial>,
}

impl MaterialTable {
    pub fn len(&self) -> usize {
        self.materials.len()
    }

    pub fn is_empty(&self) -> bool {
        self.materials.is_empty()
    }

    /// The index of the material named `name`.
    pub fn index_of(&self, name: &str) -> Option<u16> {
        self.materials
            .iter()
            .position(|m| m.name == name)
            .and_then(|i| u16::try_from(i).ok())
    }

    /// Appends a material and returns its index.
    pub fn push(&mut self, name: impl Into<String>, material: Material) -> u16 {
        self.materials.push(NamedMaterial {
            name: name.into(),
            material,
        });
        // Tables stay far below u16::MAX entries: scenes use one-character symbols.
        (self.materials.len() - 1) as u16
    }

    /// The bare materials, in table order.
    pub fn physics(&self) -> Vec<Material> {
        self.materials.iter().map(|m| m.material).collect()
    }
}

/// `sigma_a` in JSON and TOML: a number, or the string `"inf"` for opaque.
mod sigma_a_serde {
    use serde::{de, Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
        if *v == f64::INFINITY {
            s.serialize_str("inf")
        } else {
            s.serialize_f64(*v)
        }
    }

    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Raw {
        Number(f64),
        Text(String),
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        match Raw::deserialize(d)? {
            Raw::Number(v) => Ok(v),
            Raw::Text(t) if t == "inf" => Ok(f64::INFINITY),
            Raw::Text(t) => Err(de::Error::custom(format!(
                "sigma_a must be a number >= 0 or \"inf\", got {t:?}"
            ))),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validation_rejects_out_of_range_values() {
        assert!(Material::new(0.5, 0.1, 0.3).is_ok());
        assert!(Material::new(0.0, f64::INFINITY, 0.0).unwrap().is_opaque());
        assert_eq!(
            Material::new(-0.1, 0.0, 0.0),
            Err(MaterialError::SigmaS(-0.1))
        );
        assert!(matches!(
            Material::new(f64::NAN, 0.0, 0.0),
            Err(MaterialError::SigmaS(_))
        ));
        assert!(matches!(
            Material::new(f64::INFINITY, 0.0, 0.0),
            Err(MaterialError::SigmaS(_))
        ));
        assert!(matches!(
            Material::new(0.0, -1.0, 0.0),
            Err(MaterialError::SigmaA(_))
        ));
        assert!(matches!(
            Material::new(0.0, f64::NAN, 0.0),
            Err(MaterialError::SigmaA(_))
        ));
        assert!(matches!(
            Material::new(0.0, 0.0, 1.01),
            Err(MaterialError::G(_))
        ));
        assert!(Material::new(0.0, 0.0, -1.0).is_ok());
    }

    #[test]
    fn opaque_round_trips_as_inf_in_json() {
        let json = serde_json_like(&Material::OPAQUE);
        assert!(json.contains("\"inf\""), "{json}");
    }

    fn serde_json_like(m: &Material) -> String {
        toml::to_string(m).unwrap_or_default()
    }
}
