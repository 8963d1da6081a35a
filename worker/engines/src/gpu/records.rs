//! The records the shader reads, defined once as `#[repr(C)]` [`bytemuck::Pod`] structs that the
//! WGSL structs of `shaders/transport.wgsl` mirror field for field, and the batch laid out in
//! them on the host ([`HostLayout`]).
//!
//! Each record is declared with [`shader_record!`], which also lists its fields (name, offset,
//! size, type) in `FIELDS`; a test reflects the shader with naga and checks that the WGSL struct
//! of the same name has the same fields in the same order at the same offsets and sizes.

use crate::rules::{start_pixel, uniform_block_levels, CORNER_TOLERANCE_F32};
use scatterfarm_model::engine::{RenderBatch, RenderItem};
use scatterfarm_model::geometry::Geometry;
use scatterfarm_model::material::Material;

/// The largest HG `c = (1−g)/(1+g)` the shader gets: beyond it (g within 2e-18 of −1) the turn
/// is a full reversal to f32 precision, and c² must not overflow f32.
const MAX_HG_C: f64 = 1e18;

/// One field of a shader record, as the host lays it out.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct RecordField {
    pub(crate) name: &'static str,
    pub(crate) offset: usize,
    pub(crate) size: usize,
    /// The Rust type as written: `f32`, `u32`, `[f32; 2]`, ...
    pub(crate) ty: &'static str,
}

/// Declares a `#[repr(C)]`, `Pod` record mirrored by a WGSL struct of the same name, with its
/// field table `FIELDS` (checked against the shader by the GPU tests).
macro_rules! shader_record {
    (
        $(#[$meta:meta])*
        pub(crate) struct $name:ident {
            $($(#[$field_meta:meta])* pub(crate) $field:ident: $ty:ty,)*
        }
    ) => {
        $(#[$meta])*
        #[repr(C)]
        #[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
        pub(crate) struct $name {
            $($(#[$field_meta])* pub(crate) $field: $ty,)*
        }

        impl $name {
            /// The WGSL struct this record mirrors.
            #[allow(dead_code)]
            pub(crate) const WGSL_NAME: &'static str = stringify!($name);
            /// The fields in order, as laid out here.
            #[allow(dead_code)]
            pub(crate) const FIELDS: &'static [RecordField] = &[$(RecordField {
                name: stringify!($field),
                offset: std::mem::offset_of!($name, $field),
                size: std::mem::size_of::<$ty>(),
                ty: stringify!($ty),
            }),*];
        }
    };
}

shader_record! {
    /// A dispatch's parameters (`Params` in `transport.wgsl`), read through a dynamic uniform
    /// offset: one record per dispatch.
    pub(crate) struct Params {
        /// Side W of the medium (mm).
        pub(crate) size_mm: f32,
        /// Pixel side h = W / N.
        pub(crate) pixel: f32,
        /// 1/h.
        pub(crate) inv_pixel: f32,
        /// 1/e for the extent e = 4W / P.
        pub(crate) inv_extent: f32,
        /// [`CORNER_TOLERANCE_F32`] · W: the shader's corner and grid-line tolerance (mm).
        pub(crate) corner_tol: f32,
        /// N.
        pub(crate) grid: u32,
        /// P.
        pub(crate) positions: u32,
        /// K.
        pub(crate) directions: u32,
        /// P·K sources (= bins).
        pub(crate) sources: u32,
        /// The photon range of every row ...
        pub(crate) photon_first: u32,
        pub(crate) photon_count: u32,
        /// ... and its split into runs of `per_invocation` photons, `splits` of them.
        pub(crate) per_invocation: u32,
        pub(crate) splits: u32,
        /// This dispatch's tasks.
        pub(crate) task_first: u32,
        pub(crate) task_count: u32,
        /// The chunk's rows: local item r / source_count, source source_first + r % source_count.
        pub(crate) source_first: u32,
        pub(crate) source_count: u32,
        /// Padding to the uniform layout's 16-byte multiple.
        pub(crate) pad0: u32,
        pub(crate) pad1: u32,
        pub(crate) pad2: u32,
    }
}

shader_record! {
    /// A source's ideal ray (`Source` in `transport.wgsl`), computed in f64 on the host.
    pub(crate) struct Source {
        /// Origin (mm).
        pub(crate) origin: [f32; 2],
        /// Unit direction.
        pub(crate) dir: [f32; 2],
        /// The pixel (column, row from the bottom) the ray starts in, after the grid-line rule.
        pub(crate) start: [u32; 2],
    }
}

shader_record! {
    /// A differential render's sizes (`Differential` in `differential.wgsl`), one uniform record.
    pub(crate) struct Differential {
        /// Changes in the render.
        pub(crate) changes: u32,
        /// Materials in the table.
        pub(crate) materials: u32,
        /// Pixels N².
        pub(crate) cells: u32,
        /// 32-bit words of one invocation's scratch slot.
        pub(crate) slot_words: u32,
    }
}

shader_record! {
    /// One table material as a change's weight needs it (`Physics` in `differential.wgsl`).
    pub(crate) struct Physics {
        /// σt, 0 for opaque.
        pub(crate) sigma_t: f32,
        /// ln σs (−∞ for σs = 0: unused then).
        pub(crate) ln_sigma_s: f32,
        /// ln(1 − g²).
        pub(crate) ln_norm: f32,
        /// g.
        pub(crate) g: f32,
        /// 1 when σs > 0.
        pub(crate) scatters: u32,
        /// 1 when opaque.
        pub(crate) opaque: u32,
        /// Padding to 32 bytes.
        pub(crate) pad0: u32,
        pub(crate) pad1: u32,
    }
}

impl Physics {
    pub(crate) fn of(m: &Material) -> Physics {
        let opaque = m.is_opaque();
        Physics {
            sigma_t: if opaque { 0.0 } else { m.sigma_t() as f32 },
            // Finite stand-ins where the logarithm is −∞ (σs = 0, |g| = 1): the shader may assume
            // finite numbers, and no reweightable change reads these then.
            ln_sigma_s: m.sigma_s.ln().max(-100.0) as f32,
            ln_norm: (1.0 - m.g * m.g).ln().max(-100.0) as f32,
            g: m.g as f32,
            scatters: u32::from(m.sigma_s > 0.0),
            opaque: u32::from(opaque),
            pad0: 0,
            pad1: 0,
        }
    }
}

/// Bytes of a differential render's uniform record.
pub(crate) const DIFFERENTIAL_BYTES: u64 = std::mem::size_of::<Differential>() as u64;

/// Bytes of one material's record for the differential render.
pub(crate) const PHYSICS_BYTES: u64 = std::mem::size_of::<Physics>() as u64;

/// Bytes of one parameter record.
pub(crate) const PARAMS_BYTES: u64 = std::mem::size_of::<Params>() as u64;

/// Bytes of one source record.
pub(crate) const SOURCE_BYTES: u64 = std::mem::size_of::<Source>() as u64;

/// Bytes of one item's seed.
pub(crate) const SEED_BYTES: u64 = std::mem::size_of::<Seed>() as u64;

/// One pixel of the medium buffer (`vec4<f32>`): σt or −1 for opaque, uniform-block level,
/// σa/σt, HG c or −1 for g = −1.
pub(crate) type Pixel = [f32; 4];

/// One item's seed as (low, high) words (`vec2<u32>`).
pub(crate) type Seed = [u32; 2];

impl Params {
    /// The geometry's part of a record; the work fields are zero.
    pub(crate) fn for_geometry(g: &Geometry) -> Params {
        Params {
            size_mm: g.size_mm as f32,
            pixel: g.pixel_size() as f32,
            inv_pixel: (1.0 / g.pixel_size()) as f32,
            inv_extent: (1.0 / g.extent()) as f32,
            corner_tol: (CORNER_TOLERANCE_F32 * g.size_mm) as f32,
            grid: g.grid,
            positions: g.positions,
            directions: g.directions,
            sources: g.sources() as u32,
            ..bytemuck::Zeroable::zeroed()
        }
    }
}

/// The batch laid out for the shader: per source, per item.
pub(crate) struct HostLayout {
    /// The sources' records.
    pub(crate) sources: Vec<Source>,
    /// Per item: per pixel `iy · N + ix` (`iy` from the bottom) its record.
    pub(crate) medium: Vec<Vec<Pixel>>,
    /// Per item: its seed.
    pub(crate) seeds: Vec<Seed>,
}

impl HostLayout {
    pub(crate) fn new(batch: &RenderBatch<'_>) -> HostLayout {
        let geo = batch.geometry;
        let sources = (0..geo.sources())
            .map(|i| {
                let ray = geo.source_ray(i);
                let (ix, iy) = start_pixel(&geo, ray.origin, ray.direction);
                Source {
                    origin: ray.origin.map(|v| v as f32),
                    dir: ray.direction.map(|v| v as f32),
                    start: [ix as u32, iy as u32],
                }
            })
            .collect();
        let cells: Vec<CellMaterial> = batch.table.iter().map(CellMaterial::new).collect();
        let n = geo.grid as usize;
        let mut medium = Vec::with_capacity(batch.items.len());
        let mut seeds = Vec::with_capacity(batch.items.len());
        for RenderItem { assignment, seed } in batch.items {
            // Bottom-up pixel order, as the shader indexes pixels.
            let pixels: Vec<u16> = (0..n)
                .flat_map(|iy| assignment[(n - 1 - iy) * n..(n - iy) * n].iter().copied())
                .collect();
            let levels = uniform_block_levels(&pixels, n);
            medium.push(
                pixels
                    .iter()
                    .zip(&levels)
                    .map(|(&m, &level)| {
                        // validate_batch checked every index against the table.
                        let c = cells[usize::from(m)];
                        [c.sigma_t, f32::from(level), c.absorb, c.hg_c]
                    })
                    .collect(),
            );
            seeds.push([*seed as u32, (*seed >> 32) as u32]);
        }
        HostLayout {
            sources,
            medium,
            seeds,
        }
    }
}

/// One material as the shader reads it.
#[derive(Debug, Clone, Copy)]
struct CellMaterial {
    /// σt, or −1 for opaque.
    sigma_t: f32,
    /// σa/σt (0 for transmissive and opaque).
    absorb: f32,
    /// HG c = (1−g)/(1+g), at most [`MAX_HG_C`], or −1 for g = −1 (full reversal).
    hg_c: f32,
}

impl CellMaterial {
    fn new(m: &Material) -> CellMaterial {
        let sigma_t = m.sigma_t();
        let opaque = m.is_opaque();
        CellMaterial {
            sigma_t: if opaque { -1.0 } else { sigma_t as f32 },
            absorb: if sigma_t > 0.0 && !opaque {
                (m.sigma_a / sigma_t) as f32
            } else {
                0.0
            },
            hg_c: if m.g <= -1.0 {
                -1.0
            } else {
                ((1.0 - m.g) / (1.0 + m.g)).min(MAX_HG_C) as f32
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::device::WORKGROUP_SIZE;
    use super::super::shader_source;
    use super::*;
    use naga::{Expression, Literal, Module, ScalarKind, Type, TypeInner};

    fn module() -> Module {
        let source = shader_source(false);
        naga::front::wgsl::parse_str(&source)
            .unwrap_or_else(|e| panic!("{}", e.emit_to_string(&source)))
    }

    /// A WGSL scalar or vector type written as the Rust type that mirrors it.
    fn rust_name(ty: &Type) -> String {
        let scalar = |s: naga::Scalar| match (s.kind, s.width) {
            (ScalarKind::Float, 4) => "f32".to_string(),
            (ScalarKind::Uint, 4) => "u32".to_string(),
            (ScalarKind::Sint, 4) => "i32".to_string(),
            other => format!("{other:?}"),
        };
        match &ty.inner {
            TypeInner::Scalar(s) => scalar(*s),
            TypeInner::Vector { size, scalar: s } => format!("[{}; {}]", scalar(*s), *size as u8),
            other => format!("{other:?}"),
        }
    }

    /// Every `shader_record!` struct has a WGSL struct of the same name with the same fields, in
    /// the same order, at the same offsets, of the same types and sizes, and the same size.
    #[test]
    fn wgsl_structs_mirror_the_host_records() {
        let module = module();
        let records: [(&str, &[RecordField], usize); 4] = [
            (
                Params::WGSL_NAME,
                Params::FIELDS,
                std::mem::size_of::<Params>(),
            ),
            (
                Source::WGSL_NAME,
                Source::FIELDS,
                std::mem::size_of::<Source>(),
            ),
            (
                Differential::WGSL_NAME,
                Differential::FIELDS,
                std::mem::size_of::<Differential>(),
            ),
            (
                Physics::WGSL_NAME,
                Physics::FIELDS,
                std::mem::size_of::<Physics>(),
            ),
        ];
        for (name, fields, size) in records {
            let (_, ty) = module
                .types
                .iter()
                .find(|(_, t)| t.name.as_deref() == Some(name))
                .unwrap_or_else(|| panic!("the shader has no struct {name}"));
            let TypeInner::Struct { members, span } = &ty.inner else {
                panic!("{name} is not a struct in the shader");
            };
            let wgsl: Vec<(String, usize, usize, String)> = members
                .iter()
                .map(|m| {
                    let t = &module.types[m.ty];
                    let size = t.inner.size(module.to_ctx()) as usize;
                    let name = m.name.clone().unwrap_or_default();
                    (name, m.offset as usize, size, rust_name(t))
                })
                .collect();
            let rust: Vec<(String, usize, usize, String)> = fields
                .iter()
                .map(|f| (f.name.to_string(), f.offset, f.size, f.ty.to_string()))
                .collect();
            assert_eq!(
                wgsl, rust,
                "{name}: WGSL fields (left) against Rust (right)"
            );
            assert_eq!(*span as usize, size, "{name}: WGSL size against Rust");
        }
    }

    /// The bindings hold what the host uploads: the uniform one parameter record, the storage
    /// arrays elements of the host's record sizes.
    #[test]
    fn wgsl_bindings_have_the_host_record_sizes() {
        let module = module();
        let expected: [(u32, usize); 11] = [
            (0, std::mem::size_of::<Params>()),
            (1, std::mem::size_of::<Source>()),
            (2, std::mem::size_of::<Pixel>()),
            (3, std::mem::size_of::<Seed>()),
            (4, 4),
            (5, 4),
            (6, std::mem::size_of::<Differential>()),
            (7, 4),
            (8, std::mem::size_of::<Physics>()),
            (9, 4),
            (10, 4),
        ];
        assert_eq!(
            PARAMS_BYTES % 16,
            0,
            "uniform records are 16-byte multiples"
        );
        for (binding, size) in expected {
            let (_, var) = module
                .global_variables
                .iter()
                .find(|(_, v)| {
                    v.binding
                        .as_ref()
                        .is_some_and(|b| b.group == 0 && b.binding == binding)
                })
                .unwrap_or_else(|| panic!("the shader has no binding {binding}"));
            let element = match &module.types[var.ty].inner {
                TypeInner::Array { stride, .. } => *stride as usize,
                inner => inner.size(module.to_ctx()) as usize,
            };
            assert_eq!(
                element, size,
                "binding {binding}: WGSL element bytes against the host's"
            );
        }
    }

    fn literal(module: &Module, init: naga::Handle<Expression>) -> Literal {
        match module.global_expressions[init] {
            Expression::Literal(l) => l,
            ref other => panic!("not a literal: {other:?}"),
        }
    }

    /// The constants the shader shares with the host agree with the Rust ones: the bin snap of
    /// `Geometry::bin_of_exit`, and the workgroup size the pipeline overrides.
    #[test]
    fn wgsl_constants_agree_with_the_host() {
        let module = module();
        let (_, snap) = module
            .constants
            .iter()
            .find(|(_, c)| c.name.as_deref() == Some("BIN_SNAP"))
            .expect("the shader has no BIN_SNAP");
        assert_eq!(
            literal(&module, snap.init),
            Literal::F32(scatterfarm_model::geometry::BIN_SNAP as f32)
        );
        let (_, workgroup) = module
            .overrides
            .iter()
            .find(|(_, o)| o.name.as_deref() == Some("WORKGROUP_SIZE"))
            .expect("the shader has no WORKGROUP_SIZE override");
        let init = workgroup.init.expect("WORKGROUP_SIZE has no default");
        assert_eq!(literal(&module, init), Literal::U32(WORKGROUP_SIZE));
    }

    /// The shader's corner and grid-line tolerance is the host's rule, scaled by W.
    #[test]
    fn params_carry_the_shared_tolerance() {
        let geo = Geometry::default();
        let p = Params::for_geometry(&geo);
        assert_eq!(p.corner_tol, (CORNER_TOLERANCE_F32 * geo.size_mm) as f32);
        assert_eq!(p.sources as usize, geo.sources());
        assert_eq!(bytemuck::bytes_of(&p).len() as u64, PARAMS_BYTES);
    }
}
