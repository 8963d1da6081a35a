//! A render's identity (`docs/model.md`, "Render identity"): material assignment, material table, geometry, seed,
//! photons per source and engine fingerprint, hashed. Equal identities give equal counts, so a
//! score is cached under its render's identity.

use scatterfarm_model::{Geometry, Material};
use sha2::{Digest, Sha256};

/// The SHA-256 of a render's identity.
pub type Identity = [u8; 32];

/// The SHA-256 of a render's identity.
pub fn identity(
    assignment: &[u16],
    table: &[Material],
    geometry: Geometry,
    seed: u64,
    photons: u32,
    fingerprint: &str,
) -> Identity {
    let mut h = Sha256::new();
    h.update(b"scatterfarm-render/1\0");
    h.update(geometry.size_mm.to_le_bytes());
    for v in [
        geometry.grid,
        geometry.positions,
        geometry.directions,
        photons,
    ] {
        h.update(v.to_le_bytes());
    }
    h.update(seed.to_le_bytes());
    h.update((table.len() as u64).to_le_bytes());
    for m in table {
        for v in [m.sigma_s, m.sigma_a, m.g] {
            h.update(v.to_le_bytes());
        }
    }
    h.update((assignment.len() as u64).to_le_bytes());
    for a in assignment {
        h.update(a.to_le_bytes());
    }
    h.update(fingerprint.as_bytes());
    h.finalize().into()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_part_of_the_identity_counts() {
        let g = Geometry {
            size_mm: 16.0,
            grid: 2,
            positions: 8,
            directions: 3,
        };
        let t = [Material {
            sigma_s: 1.0,
            sigma_a: 0.0,
            g: 0.0,
        }];
        let base = identity(&[0; 4], &t, g, 1, 10, "cpu");
        assert_eq!(base, identity(&[0; 4], &t, g, 1, 10, "cpu"));
        assert_ne!(base, identity(&[0; 4], &t, g, 2, 10, "cpu"));
        assert_ne!(base, identity(&[0; 4], &t, g, 1, 11, "cpu"));
        assert_ne!(base, identity(&[0; 4], &t, g, 1, 10, "gpu"));
        let g2 = Geometry { positions: 12, ..g };
        assert_ne!(base, identity(&[0; 4], &t, g2, 1, 10, "cpu"));
        let t2 = [Material { g: 0.5, ..t[0] }];
        assert_ne!(base, identity(&[0; 4], &t2, g, 1, 10, "cpu"));
    }
}
