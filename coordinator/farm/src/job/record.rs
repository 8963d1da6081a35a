//! A job's immutable record: what never changes after submission, and how it is read back.

use scatterfarm_job::spec::JobSpec;
use serde::{Deserialize, Serialize};

/// What never changes after submission.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct JobRecord {
    pub params: JobSpec,
    /// The names of the input files, stored as blobs `input/NAME`.
    pub files: Vec<String>,
    pub submitted_unix: f64,
}

/// A stored job record, its spec of a layout this build reads.
pub(super) fn record_from_json(bytes: &[u8]) -> Result<JobRecord, String> {
    let record: JobRecord = serde_json::from_slice(bytes).map_err(|e| e.to_string())?;
    record.params.check_version().map_err(|e| e.to_string())?;
    Ok(record)
}

/// The blob key of the input file `name`.
pub(super) fn input_key(name: &str) -> String {
    format!("input/{name}")
}

/// Seconds since the Unix epoch, now.
pub(super) fn now_unix() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_read_back_and_another_spec_version_is_refused() {
        let record = JobRecord {
            params: JobSpec {
                scene: Some("demo8".into()),
                permutations: 2,
                ..Default::default()
            },
            files: vec![],
            submitted_unix: 2.0,
        };
        let bytes = serde_json::to_vec(&record).unwrap();
        assert_eq!(record_from_json(&bytes).unwrap().params, record.params);
        let mut later = record.clone();
        later.params.version += 1;
        let err = record_from_json(&serde_json::to_vec(&later).unwrap()).unwrap_err();
        assert!(err.contains("`version`"), "{err}");
        assert!(record_from_json(b"{").is_err());
    }
}
