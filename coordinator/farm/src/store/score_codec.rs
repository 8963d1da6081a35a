//! A render's score as stored bytes, and back.

use super::StoreError;
use scatterfarm_search::{Score, Secondary};

/// A stored score: value, step and standard error (little-endian f64, u64, f64); then, when
/// there is a secondary score, its value and error; then, when there are likelihood blocks,
/// their count (u64) and values. The secondary is present when the remainder after the first
/// three words is 16 bytes, or 16 bytes plus a block list; a block list alone starts right
/// after the first three words. The two cases are told apart by the block count.
pub fn encode_score(score: &Score, step: u64) -> Vec<u8> {
    let mut value = Vec::with_capacity(40 + 8 * (score.blocks.len() + 1));
    value.extend_from_slice(&score.value.to_le_bytes());
    value.extend_from_slice(&step.to_le_bytes());
    value.extend_from_slice(&score.std_error.to_le_bytes());
    if let Some(s) = score.secondary {
        value.extend_from_slice(&s.value.to_le_bytes());
        value.extend_from_slice(&s.std_error.to_le_bytes());
    }
    if !score.blocks.is_empty() {
        value.extend_from_slice(&(score.blocks.len() as u64).to_le_bytes());
        for b in &score.blocks {
            value.extend_from_slice(&b.to_le_bytes());
        }
    }
    value
}

/// The inverse of [`encode_score`]; a record of any other shape is damaged.
pub fn decode_score(v: &[u8]) -> Result<(Score, u64), StoreError> {
    let damaged = || StoreError::Damaged {
        what: "score",
        detail: format!("{} bytes", v.len()),
    };
    if v.len() < 24 || !v.len().is_multiple_of(8) {
        return Err(damaged());
    }
    let words: Vec<[u8; 8]> = v
        .chunks_exact(8)
        .map(|c| {
            let mut b = [0u8; 8];
            b.copy_from_slice(c);
            b
        })
        .collect();
    let f = |i: usize| f64::from_le_bytes(words[i]);
    let rest = words.len() - 3;
    // A block list at word `at`: its count fills the rest exactly.
    let blocks_at = |at: usize| -> Option<Vec<f64>> {
        let n = u64::from_le_bytes(*words.get(at)?);
        (n > 0 && usize::try_from(n).ok()? == words.len() - at - 1)
            .then(|| (at + 1..words.len()).map(f).collect())
    };
    let (secondary, blocks) = match rest {
        0 => (None, Vec::new()),
        2 if blocks_at(3).is_none() => (
            Some(Secondary {
                value: f(3),
                std_error: f(4),
            }),
            Vec::new(),
        ),
        _ => match blocks_at(3) {
            Some(b) => (None, b),
            None => match blocks_at(5) {
                Some(b) => (
                    Some(Secondary {
                        value: f(3),
                        std_error: f(4),
                    }),
                    b,
                ),
                None => return Err(damaged()),
            },
        },
    };
    Ok((
        Score {
            value: f(0),
            std_error: f(2),
            secondary,
            blocks,
            changes: Vec::new(),
        },
        u64::from_le_bytes(words[1]),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scores_round_trip_in_every_shape_and_damage_is_named() {
        let shapes = [
            Score::exact(0.25),
            Score {
                secondary: Some(Secondary {
                    value: -1.0,
                    std_error: 0.5,
                }),
                ..Score::exact(0.5)
            },
            Score {
                blocks: vec![-1.5, -2.0, -0.25],
                changes: Vec::new(),
                ..Score::exact(-3.75)
            },
            Score {
                secondary: Some(Secondary {
                    value: 3.0,
                    std_error: 1.0,
                }),
                blocks: vec![-4.0, -5.0],
                changes: Vec::new(),
                ..Score::exact(-9.0)
            },
        ];
        for (step, score) in shapes.into_iter().enumerate() {
            let bytes = encode_score(&score, step as u64);
            assert_eq!(decode_score(&bytes).unwrap(), (score, step as u64));
        }
        assert!(decode_score(&[0; 23]).is_err());
        assert!(decode_score(&[0; 25]).is_err());
        // A block count that does not fill the record.
        let mut bad = encode_score(
            &Score {
                blocks: vec![1.0, 2.0],
                changes: Vec::new(),
                ..Score::exact(0.0)
            },
            0,
        );
        bad.truncate(bad.len() - 8);
        bad.extend_from_slice(&[0; 16]);
        assert!(decode_score(&bad).is_err());
    }
}
