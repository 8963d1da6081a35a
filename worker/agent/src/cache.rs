//! What a worker keeps of the jobs it renders for, so their tasks can come without it: their
//! geometries ([`GeometryCache`], `LeaseRequest.cached_jobs`) and the targets it scores their
//! differential and scored renders against ([`TargetCache`], `LeaseRequest.cached_targets`).
//! Bounded, in jobs and (targets) in bytes: the least recently used job is forgotten first.

use scatterfarm_model::geometry::Geometry;
use scatterfarm_model::likelihood::Target;
use scatterfarm_proto::convert::{geometry_from_proto, ConvertError};
use scatterfarm_proto::differential::target_from_proto;
use scatterfarm_proto::v1::Task;
use std::collections::VecDeque;
use std::sync::Arc;

/// Values kept per job, most recently used last; the least recently used goes first.
#[derive(Debug, Clone)]
struct PerJob<T> {
    entries: VecDeque<(String, T)>,
    capacity: usize,
    /// The most bytes of values held (one value is always held, whatever its size).
    budget: usize,
    /// A value's bytes.
    weight: fn(&T) -> usize,
}

impl<T: Clone> PerJob<T> {
    fn new(capacity: usize) -> Self {
        PerJob::within(capacity, usize::MAX, |_| 0)
    }

    fn within(capacity: usize, budget: usize, weight: fn(&T) -> usize) -> Self {
        PerJob {
            entries: VecDeque::new(),
            capacity: capacity.max(1),
            budget,
            weight,
        }
    }

    /// The jobs held, sorted.
    fn jobs(&self) -> Vec<String> {
        let mut jobs: Vec<String> = self.entries.iter().map(|(j, _)| j.clone()).collect();
        jobs.sort();
        jobs
    }

    /// The job's value, now the most recently used.
    fn get(&mut self, job: &str) -> Option<T> {
        let position = self.entries.iter().position(|(j, _)| j == job)?;
        let entry = self.entries.remove(position)?;
        let value = entry.1.clone();
        self.entries.push_back(entry);
        Some(value)
    }

    /// Keeps `value` for `job`, replacing what it had.
    fn insert(&mut self, job: &str, value: T) {
        self.entries.retain(|(j, _)| j != job);
        let weight = self.weight;
        let mut held: usize = self.entries.iter().map(|(_, v)| weight(v)).sum();
        while !self.entries.is_empty()
            && (self.entries.len() >= self.capacity
                || held.saturating_add(weight(&value)) > self.budget)
        {
            if let Some((_, v)) = self.entries.pop_front() {
                held -= weight(&v);
            }
        }
        self.entries.push_back((job.to_string(), value));
    }
}

/// Job geometries.
#[derive(Debug, Clone)]
pub(crate) struct GeometryCache(PerJob<Geometry>);

impl GeometryCache {
    pub const CAPACITY: usize = scatterfarm_proto::convert::WORKER_CACHE_JOBS;

    pub fn new(capacity: usize) -> Self {
        GeometryCache(PerJob::new(capacity))
    }

    /// The jobs to name in a lease request, sorted.
    pub fn jobs(&self) -> Vec<String> {
        self.0.jobs()
    }

    /// The geometry `task` renders over: its own (cached when it is the job's), else the job's
    /// cached one, else [`ConvertError::MissingGeometry`].
    pub fn resolve(&mut self, task: &Task) -> Result<Geometry, ConvertError> {
        if let Some(g) = &task.geometry {
            let geometry = geometry_from_proto(g)?;
            if task.geometry_is_job_geometry {
                self.0.insert(&task.job_id, geometry);
            }
            return Ok(geometry);
        }
        self.0
            .get(&task.job_id)
            .ok_or_else(|| ConvertError::MissingGeometry {
                job_id: task.job_id.clone(),
            })
    }
}

/// Job targets: as many jobs as geometries, within [`TargetCache::BYTES`] (a target is
/// `sources × bins` values: 5.3 MB at 1152 × 1152, so about 100 of those).
#[derive(Debug, Clone)]
pub(crate) struct TargetCache(PerJob<Arc<Target>>);

impl TargetCache {
    pub const CAPACITY: usize = scatterfarm_proto::convert::WORKER_CACHE_JOBS;
    /// The most bytes of targets kept.
    pub const BYTES: usize = 512 << 20;

    pub fn new(capacity: usize, bytes: usize) -> Self {
        TargetCache(PerJob::within(capacity, bytes, |t| {
            t.values.len() * std::mem::size_of::<f32>()
        }))
    }

    /// The jobs to name in a lease request, sorted.
    pub fn jobs(&self) -> Vec<String> {
        self.0.jobs()
    }

    /// The target a differential or scored `task` over `geometry` scores against: the one it
    /// carries (checked, then kept), else the job's cached one.
    pub fn resolve(
        &mut self,
        task: &Task,
        geometry: &Geometry,
    ) -> Result<Arc<Target>, ConvertError> {
        let observations = geometry.sources() * geometry.bins();
        let carried = task
            .differential
            .as_ref()
            .and_then(|d| d.target.as_ref())
            .or_else(|| task.scored.as_ref().and_then(|s| s.target.as_ref()));
        if let Some(t) = carried {
            let target = Arc::new(target_from_proto(t, observations)?);
            self.0.insert(&task.job_id, target.clone());
            return Ok(target);
        }
        let target = self.0.get(&task.job_id).ok_or_else(|| {
            ConvertError::Target(format!(
                "the task of job {} came without one and it is not cached",
                task.job_id
            ))
        })?;
        if target.values.len() != observations {
            return Err(ConvertError::Target(format!(
                "the cached target of job {} has {} values, the task's geometry {observations}",
                task.job_id,
                target.values.len()
            )));
        }
        Ok(target)
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

    fn differential_task(job: &str, target: Option<&Target>) -> Task {
        Task {
            job_id: job.into(),
            differential: Some(scatterfarm_proto::v1::Differential {
                target: target.map(scatterfarm_proto::differential::target_to_proto),
                ..Default::default()
            }),
            ..Task::default()
        }
    }

    #[test]
    fn targets_are_kept_per_job_checked_against_the_geometry_and_forgotten_oldest_first() {
        let g = Geometry::new(8.0, 4, 8, 1).unwrap();
        let n = g.sources() * g.bins();
        let target = |v: f32| Target {
            values: vec![v; n],
            photons_per_source: 100,
        };
        let mut cache = TargetCache::new(2, usize::MAX);
        assert!(matches!(
            cache.resolve(&differential_task("a", None), &g),
            Err(ConvertError::Target(_))
        ));
        let a = cache
            .resolve(&differential_task("a", Some(&target(0.25))), &g)
            .unwrap();
        assert_eq!(a.values, target(0.25).values);
        // Later tasks of the job come without it and get the cached one.
        let again = cache.resolve(&differential_task("a", None), &g).unwrap();
        assert_eq!(again.values, a.values);
        // A target of the wrong length is refused, on the wire and from the cache.
        let other = Geometry::new(8.0, 4, 16, 1).unwrap();
        assert!(matches!(
            cache.resolve(&differential_task("a", None), &other),
            Err(ConvertError::Target(_))
        ));
        assert!(matches!(
            cache.resolve(&differential_task("b", Some(&target(0.5))), &other),
            Err(ConvertError::Target(_))
        ));
        assert_eq!(cache.jobs(), ["a"]);
        // A resent target replaces the cached one.
        let replaced = cache
            .resolve(&differential_task("a", Some(&target(0.5))), &g)
            .unwrap();
        assert_eq!(replaced.values[0], 0.5);
        cache
            .resolve(&differential_task("b", Some(&target(0.1))), &g)
            .unwrap();
        cache.resolve(&differential_task("a", None), &g).unwrap();
        cache
            .resolve(&differential_task("c", Some(&target(0.1))), &g)
            .unwrap();
        assert_eq!(cache.jobs(), ["a", "c"]);
        assert!(cache.resolve(&differential_task("b", None), &g).is_err());
        // Within a byte budget of two targets and a half, three jobs keep two.
        let mut bytes = TargetCache::new(8, 4 * n * 5 / 2);
        for job in ["a", "b", "c"] {
            bytes
                .resolve(&differential_task(job, Some(&target(0.1))), &g)
                .unwrap();
        }
        assert_eq!(bytes.jobs(), ["b", "c"]);
        // One target larger than the budget is still kept, alone.
        let mut small = TargetCache::new(8, 1);
        small
            .resolve(&differential_task("a", Some(&target(0.1))), &g)
            .unwrap();
        small
            .resolve(&differential_task("b", Some(&target(0.1))), &g)
            .unwrap();
        assert_eq!(small.jobs(), ["b"]);
    }
}
