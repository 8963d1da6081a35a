//! The differential parts of the protocol and their checks: a task's changes and chunk size
//! ([`DifferentialPart`]), the job's target a worker scores against, and the score of every
//! change the worker returns. Like [`crate::convert`], both ends encode and check here.

use crate::convert::ConvertError;
use crate::v1;
use bytes::Bytes;
use scatterfarm_model::differential::Change;
use scatterfarm_model::likelihood::{Deviance, Target, MAX_BLOCKS};

/// The most changes one differential task may estimate (a sweep of a 64×64 map over four
/// alternatives is 16 384).
pub const MAX_CHANGES: usize = 1 << 16;

/// What a differential task adds to a render: the changes it estimates, and the chunk size its
/// photons are rendered in.
#[derive(Debug, Clone, PartialEq)]
pub struct DifferentialPart {
    pub changes: Vec<Change>,
    pub chunk: u32,
}

/// The wire form of a differential part, with `target` when the worker does not hold it.
pub fn differential_to_proto(part: &DifferentialPart, target: Option<&Target>) -> v1::Differential {
    v1::Differential {
        changes: part
            .changes
            .iter()
            .map(|c| v1::Change {
                pixels: c.pixels.iter().map(|&(p, _)| p).collect(),
                materials: c.pixels.iter().map(|&(_, m)| u32::from(m)).collect(),
            })
            .collect(),
        chunk_photons: part.chunk,
        target: target.map(target_to_proto),
    }
}

/// A differential part from the wire, checked against a task of `items` assignments starting
/// at photon `first`, over `pixels` pixels and a table of `table` materials.
pub fn differential_from_proto(
    d: &v1::Differential,
    items: usize,
    first: u32,
    pixels: usize,
    table: usize,
) -> Result<DifferentialPart, ConvertError> {
    let bad = |why: String| ConvertError::Differential(why);
    if items != 1 || first != 0 {
        return Err(bad(format!(
            "a differential task renders one assignment from photon 0, not {items} from photon \
             {first}"
        )));
    }
    if d.chunk_photons == 0 {
        return Err(bad("a chunk of 0 photons".into()));
    }
    if d.changes.len() > MAX_CHANGES {
        return Err(bad(format!(
            "{} changes, more than the {MAX_CHANGES} one task may carry",
            d.changes.len()
        )));
    }
    let changes = d
        .changes
        .iter()
        .enumerate()
        .map(|(k, c)| {
            // An empty change (the map itself) is allowed: its estimate is the plain render's.
            if c.pixels.len() != c.materials.len() || c.pixels.len() > pixels {
                return Err(bad(format!(
                    "change {k}: {} pixels and {} materials (up to {pixels} of each, pairwise)",
                    c.pixels.len(),
                    c.materials.len()
                )));
            }
            c.pixels
                .iter()
                .zip(&c.materials)
                .map(|(&p, &m)| {
                    if p as usize >= pixels || m as usize >= table {
                        return Err(bad(format!(
                            "change {k}: pixel {p} to material {m}, with {pixels} pixels and {table} \
                             materials"
                        )));
                    }
                    Ok((p, m as u16))
                })
                .collect::<Result<Vec<_>, _>>()
                .map(|pixels| Change { pixels })
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(DifferentialPart {
        changes,
        chunk: d.chunk_photons,
    })
}

/// A target as the wire carries it.
pub fn target_to_proto(t: &Target) -> v1::Target {
    let mut bytes = Vec::with_capacity(4 * t.values.len());
    for v in &t.values {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    v1::Target {
        values_le_f32: Bytes::from(bytes),
        photons_per_source: t.photons_per_source,
    }
}

/// A target from the wire for a geometry of `observations` observations: that many values,
/// each finite and in [0, 1], over at least one photon per source.
pub fn target_from_proto(t: &v1::Target, observations: usize) -> Result<Target, ConvertError> {
    let bad = |why: String| ConvertError::Target(why);
    if t.values_le_f32.len() != 4 * observations {
        return Err(bad(format!(
            "{} bytes, the geometry needs {observations} f32 values ({} bytes)",
            t.values_le_f32.len(),
            4 * observations
        )));
    }
    if t.photons_per_source == 0 {
        return Err(bad("0 photons per source".into()));
    }
    let values: Vec<f32> = t
        .values_le_f32
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    if let Some((i, v)) = values
        .iter()
        .enumerate()
        .find(|(_, v)| !(0.0..=1.0).contains(*v))
    {
        return Err(bad(format!("value {i} is {v}, not a fraction in [0, 1]")));
    }
    Ok(Target {
        values,
        photons_per_source: t.photons_per_source,
    })
}

/// Every change's score as the wire carries it.
pub fn change_scores_to_proto(scores: &[Option<Deviance>]) -> Vec<v1::ChangeScore> {
    scores
        .iter()
        .map(|s| match s {
            Some(d) => v1::ChangeScore {
                estimated: true,
                value: d.value,
                blocks: d.blocks.clone(),
            },
            None => v1::ChangeScore::default(),
        })
        .collect()
}

/// Every change's score from the wire: at most [`MAX_CHANGES`], each with at most
/// [`MAX_BLOCKS`] blocks, every number finite. Whether they fit the task is the receiver's
/// check (it knows the changes and the geometry).
pub fn change_scores_from_proto(
    scores: &[v1::ChangeScore],
) -> Result<Vec<Option<Deviance>>, ConvertError> {
    let bad = |why: String| ConvertError::ChangeScores(why);
    if scores.len() > MAX_CHANGES {
        return Err(bad(format!("{} scores", scores.len())));
    }
    scores
        .iter()
        .enumerate()
        .map(|(k, s)| {
            if !s.estimated {
                return if s.blocks.is_empty() && s.value == 0.0 {
                    Ok(None)
                } else {
                    Err(bad(format!(
                        "change {k}: not estimated, yet it has a score"
                    )))
                };
            }
            if s.blocks.len() > MAX_BLOCKS {
                return Err(bad(format!(
                    "change {k}: {} blocks, at most {MAX_BLOCKS}",
                    s.blocks.len()
                )));
            }
            if !s.value.is_finite() || s.blocks.iter().any(|b| !b.is_finite()) {
                return Err(bad(format!("change {k}: a score that is not finite")));
            }
            Ok(Some(Deviance {
                value: s.value,
                blocks: s.blocks.clone(),
            }))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn part() -> DifferentialPart {
        DifferentialPart {
            changes: vec![
                Change {
                    pixels: vec![(3, 1)],
                },
                Change {
                    pixels: vec![(0, 0), (1, 1)],
                },
            ],
            chunk: 64,
        }
    }

    #[test]
    fn a_differential_part_and_its_target_round_trip_and_bad_ones_are_named() {
        let target = Target {
            values: vec![0.25, 0.0, 1.0, 0.5],
            photons_per_source: 300,
        };
        let wire = differential_to_proto(&part(), Some(&target));
        assert_eq!(differential_from_proto(&wire, 1, 0, 4, 2).unwrap(), part());
        let t = wire.target.as_ref().unwrap();
        assert_eq!(target_from_proto(t, 4).unwrap(), target);
        assert!(matches!(
            target_from_proto(t, 5),
            Err(ConvertError::Target(_))
        ));
        let mut nan = t.clone();
        nan.values_le_f32 = Bytes::from([f32::NAN.to_le_bytes(); 4].concat());
        assert!(target_from_proto(&nan, 4)
            .unwrap_err()
            .to_string()
            .contains("value 0"));

        for (items, first, pixels, table, what) in [
            (2, 0, 4, 2, "one assignment"),
            (1, 5, 4, 2, "from photon 0"),
            (1, 0, 3, 2, "pixel 3"),
            (1, 0, 4, 1, "material 1"),
        ] {
            let e = differential_from_proto(&wire, items, first, pixels, table).unwrap_err();
            assert!(e.to_string().contains(what), "{e}");
        }
        let mut odd = wire.clone();
        odd.changes[1].materials.pop();
        assert!(differential_from_proto(&odd, 1, 0, 4, 2)
            .unwrap_err()
            .to_string()
            .contains("change 1"));
        let mut none = wire;
        none.chunk_photons = 0;
        assert!(differential_from_proto(&none, 1, 0, 4, 2).is_err());
    }

    #[test]
    fn change_scores_round_trip_and_bad_ones_are_refused() {
        let scores = vec![
            None,
            Some(Deviance {
                value: -3.0,
                blocks: vec![-1.0, -2.0],
            }),
        ];
        let wire = change_scores_to_proto(&scores);
        assert_eq!(change_scores_from_proto(&wire).unwrap(), scores);
        let mut inf = wire.clone();
        inf[1].blocks[0] = f64::INFINITY;
        assert!(change_scores_from_proto(&inf).is_err());
        let mut odd = wire.clone();
        odd[0].value = -1.0;
        assert!(change_scores_from_proto(&odd).is_err());
        let mut many = wire;
        many[1].blocks = vec![0.0; MAX_BLOCKS + 1];
        assert!(change_scores_from_proto(&many).is_err());
    }
}
