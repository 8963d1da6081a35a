//! A render's score as stored bytes, and back.

use super::StoreError;
use scatterfarm_search::{ChangeScore, Score, Secondary};

/// The first word of a score that carries its changes' scores (a differential render): a NaN
/// whose payload arithmetic never produces, so no plain record starts with it.
const WITH_CHANGES: u64 = 0x7ff8_5346_4348_4731;
/// The most changes a stored score may list (far above what one sweep asks for).
const MAX_CHANGES: u64 = 1 << 20;

/// A score as stored: [`encode_plain`], or, when it has changes, [`WITH_CHANGES`], the plain
/// record's length in words, the plain record, the number of changes, and per change a word
/// `k`: 0 for a change the render did not estimate, else its value and `k − 1` blocks.
pub fn encode_score(score: &Score, step: u64) -> Vec<u8> {
    let plain = encode_plain(score, step);
    if score.changes.is_empty() {
        return plain;
    }
    let mut value = Vec::with_capacity(plain.len() + 24 + score.changes.len() * 8 * 258);
    value.extend_from_slice(&WITH_CHANGES.to_le_bytes());
    value.extend_from_slice(&((plain.len() / 8) as u64).to_le_bytes());
    value.extend_from_slice(&plain);
    value.extend_from_slice(&(score.changes.len() as u64).to_le_bytes());
    for change in &score.changes {
        match change {
            None => value.extend_from_slice(&0u64.to_le_bytes()),
            Some(c) => {
                value.extend_from_slice(&(c.blocks.len() as u64 + 1).to_le_bytes());
                value.extend_from_slice(&c.value.to_le_bytes());
                for b in &c.blocks {
                    value.extend_from_slice(&b.to_le_bytes());
                }
            }
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
    if v.len() < 16 || !v.len().is_multiple_of(8) {
        return Err(damaged());
    }
    let word = |i: usize| -> Option<u64> {
        let b = v.get(8 * i..8 * i + 8)?;
        let mut w = [0u8; 8];
        w.copy_from_slice(b);
        Some(u64::from_le_bytes(w))
    };
    if word(0) != Some(WITH_CHANGES) {
        return decode_plain(v);
    }
    let words = v.len() / 8;
    let plain_words = usize::try_from(word(1).ok_or_else(damaged)?).map_err(|_| damaged())?;
    let plain_end = plain_words
        .checked_add(2)
        .filter(|&e| e < words)
        .ok_or_else(damaged)?;
    let (mut score, step) = decode_plain(&v[16..8 * plain_end])?;
    let n = word(plain_end).ok_or_else(damaged)?;
    let mut at = plain_end + 1;
    // Every change takes at least one word, so a count beyond the words left is damage, found
    // before anything is allocated for it.
    if n > MAX_CHANGES || n > (words - at) as u64 {
        return Err(damaged());
    }
    let mut changes = Vec::with_capacity(n as usize);
    for _ in 0..n {
        let k = word(at).ok_or_else(damaged)?;
        at += 1;
        if k == 0 {
            changes.push(None);
            continue;
        }
        let k = usize::try_from(k).map_err(|_| damaged())?;
        if k > words - at {
            return Err(damaged());
        }
        let f = |i: usize| f64::from_bits(word(i).unwrap_or(0));
        changes.push(Some(ChangeScore {
            value: f(at),
            blocks: (at + 1..at + k).map(f).collect(),
        }));
        at += k;
    }
    if at != words {
        return Err(damaged());
    }
    score.changes = changes;
    Ok((score, step))
}

/// A stored plain score: value, step and standard error (little-endian f64, u64, f64); then, when
/// there is a secondary score, its value and error; then, when there are likelihood blocks,
/// their count (u64) and values. The secondary is present when the remainder after the first
/// three words is 16 bytes, or 16 bytes plus a block list; a block list alone starts right
/// after the first three words. The two cases are told apart by the block count.
fn encode_plain(score: &Score, step: u64) -> Vec<u8> {
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

/// The inverse of [`encode_plain`].
fn decode_plain(v: &[u8]) -> Result<(Score, u64), StoreError> {
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

    fn shapes_with_changes() -> Score {
        Score {
            blocks: vec![-1.0, -2.0],
            changes: vec![
                None,
                Some(ChangeScore {
                    value: -2.5,
                    blocks: vec![-1.25, -1.25],
                }),
            ],
            ..Score::exact(-3.0)
        }
    }

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
            Score {
                blocks: vec![-4.0, -5.0, -1.0],
                changes: vec![
                    Some(ChangeScore {
                        value: -7.0,
                        blocks: vec![-3.0, -3.5, -0.5],
                    }),
                    None,
                    Some(ChangeScore {
                        value: -1.0,
                        blocks: Vec::new(),
                    }),
                ],
                ..Score::exact(-10.0)
            },
        ];
        for (step, score) in shapes.into_iter().enumerate() {
            let bytes = encode_score(&score, step as u64);
            assert_eq!(decode_score(&bytes).unwrap(), (score, step as u64));
        }
        // A score with changes, cut anywhere, or with a change longer than the record.
        let full = encode_score(&shapes_with_changes(), 3);
        for cut in (8..full.len()).step_by(8) {
            assert!(decode_score(&full[..cut]).is_err(), "cut at {cut}");
        }
        let mut long = full.clone();
        let at = long.len() - 8 * 4;
        long[at..at + 8].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(decode_score(&long).is_err());
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
