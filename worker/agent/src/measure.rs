//! The throughput a worker announces when it registers: its engine's photons per second on a
//! homogeneous `moderate` medium, measured once at start.
//!
//! The measurement renders a small geometry with a growing photon count until one render takes
//! at least [`MIN_SECONDS`] (about half a second to a second of work in all), and counts
//! `sources × photons per source / seconds` of that last render.

use scatterfarm_model::engine::{Engine, EngineError, PhotonRange, RenderBatch, RenderItem};
use scatterfarm_model::geometry::Geometry;
use scatterfarm_model::material::Material;
use std::time::Instant;

/// The geometry measured on: the default medium and grid, fewer boundary samples.
pub const MEASURE_GEOMETRY: Geometry = Geometry {
    size_mm: 16.0,
    grid: 16,
    positions: 32,
    directions: 4,
};

/// The medium: every pixel the built-in `moderate` (σs 0.60, σa 0.01, g 0.75).
pub const MEASURE_MATERIAL: Material = Material {
    sigma_s: 0.60,
    sigma_a: 0.01,
    g: 0.75,
};

/// The render counted is the first to take at least this long.
pub const MIN_SECONDS: f64 = 0.3;

/// Photons per source are not raised beyond this (an engine this fast is measured on it).
const MAX_PHOTONS: u32 = 1 << 24;

/// Photons per second of `engine` on [`MEASURE_GEOMETRY`] (blocks for about a second).
pub fn photons_per_second(engine: &dyn Engine) -> Result<f64, EngineError> {
    photons_per_second_at(engine, MEASURE_GEOMETRY, MIN_SECONDS)
}

/// Photons per second of `engine` on a homogeneous [`MEASURE_MATERIAL`] medium of `geometry`,
/// from the first render that takes at least `min_seconds`.
pub fn photons_per_second_at(
    engine: &dyn Engine,
    geometry: Geometry,
    min_seconds: f64,
) -> Result<f64, EngineError> {
    geometry.validate()?;
    let table = [MEASURE_MATERIAL];
    let items = [RenderItem {
        assignment: vec![0; geometry.pixels()],
        seed: 1,
    }];
    let render = |count: u32| -> Result<f64, EngineError> {
        let start = Instant::now();
        engine.render(&RenderBatch {
            geometry,
            table: &table,
            items: &items,
            photons: PhotonRange { first: 0, count },
        })?;
        Ok(start.elapsed().as_secs_f64())
    };
    // Warm-up: thread pools, device queues.
    render(4)?;
    let mut photons: u32 = 64;
    loop {
        let seconds = render(photons)?;
        if seconds >= min_seconds || photons >= MAX_PHOTONS {
            let launched = geometry.sources() as f64 * f64::from(photons);
            return Ok(launched / seconds.max(1e-9));
        }
        // Aim the next render at twice the threshold, growing by 2× to 16×.
        let factor = if seconds > 0.0 {
            (2.0 * min_seconds / seconds).clamp(2.0, 16.0)
        } else {
            16.0
        };
        photons = (f64::from(photons) * factor).min(f64::from(MAX_PHOTONS)) as u32;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use scatterfarm_engines::cpu::CpuEngine;
    use scatterfarm_model::material::builtin_material;

    #[test]
    fn the_medium_is_the_builtin_moderate() {
        assert_eq!(builtin_material("moderate"), Some(MEASURE_MATERIAL));
        assert!(MEASURE_GEOMETRY.validate().is_ok());
    }

    #[test]
    fn cpu_rate_is_positive_and_finite() {
        let engine = CpuEngine::new();
        let tiny = Geometry::new(4.0, 4, 8, 2).unwrap();
        let start = Instant::now();
        let rate = photons_per_second_at(&engine, tiny, 0.1).unwrap();
        assert!(rate.is_finite() && rate > 0.0, "{rate}");
        assert!(start.elapsed().as_secs_f64() < 10.0);
    }

    #[test]
    fn invalid_geometry_is_an_error() {
        let bad = Geometry {
            grid: 3,
            ..MEASURE_GEOMETRY
        };
        assert!(matches!(
            photons_per_second_at(&CpuEngine::new(), bad, 0.1),
            Err(EngineError::Geometry(_))
        ));
    }
}
