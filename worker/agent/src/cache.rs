//! The geometries of the jobs this worker has rendered for, so their tasks can come without one
//! (`LeaseRequest.cached_jobs`). Bounded: the least recently used job is forgotten first.

use scatterfarm_model::geometry::Geometry;
use scatterfarm_proto::convert::{geometry_from_proto, ConvertError};
use scatterfarm_proto::v1::Task;
use std::collections::VecDeque;

/// Job geometries, most recently used last.
#[derive(Debug, Clone)]
pub(crate) struct GeometryCache {
    entries: VecDeque<(String, Geometry)>,
    capacity: usize,
}

impl GeometryCache {
    pub const CAPACITY: usize = 64;

    pub fn new(capacity: usize) -> Self {
        GeometryCache {
            entries: VecDeque::new(),
            capacity: capacity.max(1),
        }
    }

    /// The jobs to name in a lease request, sorted.
    pub fn jobs(&self) -> Vec<String> {
        let mut jobs: Vec<String> = self.entries.iter().map(|(j, _)| j.clone()).collect();
        jobs.sort();
        jobs
    }

    /// The geometry `task` renders over: its own (cached when it is the job's), else the job's
    /// cached one, else [`ConvertError::MissingGeometry`].
    pub fn resolve(&mut self, task: &Task) -> Result<Geometry, ConvertError> {
        if let Some(g) = &task.geometry {
            let geometry = geometry_from_proto(g)?;
            if task.geometry_is_job_geometry {
                self.insert(&task.job_id, geometry);
            }
            return Ok(geometry);
        }
        let position = self
            .entries
            .iter()
            .position(|(job, _)| *job == task.job_id)
            .ok_or_else(|| ConvertError::MissingGeometry {
                job_id: task.job_id.clone(),
            })?;
        let entry = self
            .entries
            .remove(position)
            .ok_or_else(|| ConvertError::MissingGeometry {
                job_id: task.job_id.clone(),
            })?;
        let geometry = entry.1;
        self.entries.push_back(entry);
        Ok(geometry)
    }

    fn insert(&mut self, job: &str, geometry: Geometry) {
        self.entries.retain(|(j, _)| j != job);
        if self.entries.len() >= self.capacity {
            self.entries.pop_front();
        }
        self.entries.push_back((job.to_string(), geometry));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use scatterfarm_proto::convert::geometry_to_proto;

    fn task(job: &str, geometry: Option<Geometry>, is_job: bool) -> Task {
        Task {
            job_id: job.into(),
            geometry: geometry.as_ref().map(geometry_to_proto),
            geometry_is_job_geometry: is_job,
            ..Task::default()
        }
    }

    #[test]
    fn job_geometries_are_cached_and_others_are_not() {
        let g = Geometry::new(8.0, 4, 8, 3).unwrap();
        let calibration = Geometry::new(8.0, 4, 16, 3).unwrap();
        let mut cache = GeometryCache::new(4);
        assert_eq!(
            cache.resolve(&task("a", None, false)),
            Err(ConvertError::MissingGeometry { job_id: "a".into() })
        );
        assert_eq!(
            cache.resolve(&task("a", Some(calibration), false)),
            Ok(calibration)
        );
        assert!(cache.jobs().is_empty());
        assert_eq!(cache.resolve(&task("a", Some(g), true)), Ok(g));
        assert_eq!(cache.jobs(), ["a"]);
        assert_eq!(cache.resolve(&task("a", None, false)), Ok(g));
        let mut bad = g;
        bad.grid = 5;
        assert!(matches!(
            cache.resolve(&task("b", Some(bad), true)),
            Err(ConvertError::Geometry(_))
        ));
        assert_eq!(cache.jobs(), ["a"]);
    }

    #[test]
    fn the_least_recently_used_job_goes_first() {
        let g = Geometry::new(8.0, 4, 8, 3).unwrap();
        let mut cache = GeometryCache::new(2);
        cache.resolve(&task("a", Some(g), true)).unwrap();
        cache.resolve(&task("b", Some(g), true)).unwrap();
        cache.resolve(&task("a", None, false)).unwrap();
        cache.resolve(&task("c", Some(g), true)).unwrap();
        assert_eq!(cache.jobs(), ["a", "c"]);
    }
}
