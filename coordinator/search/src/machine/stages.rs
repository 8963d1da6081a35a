//! What follows a level: the next level, the refinement stage (started from the last level's
//! map), or the end.

use super::*;

impl Search {
    pub(super) fn after_level(&mut self) -> Result<(), SearchError> {
        let next = self.levels.len() as u32;
        if next <= self.max_level() {
            return self.start_level(next);
        }
        self.state = None;
        match (self.config.refine.clone(), self.levels.last().cloned()) {
            (Some(config), Some(last)) => {
                let materials = match &self.config.candidates {
                    Candidates::Dictionary(d) => d.clone(),
                    Candidates::Random { .. } => distinct(&last.assignment),
                };
                let physics = self.table.physics();
                let reweightable = physics
                    .iter()
                    .map(|from| {
                        physics
                            .iter()
                            .map(|to| scatterfarm_model::differential::reweightable(from, to))
                            .collect()
                    })
                    .collect();
                let opaque = physics.iter().map(|m| m.is_opaque()).collect();
                let spread = physics
                    .iter()
                    .map(|from| {
                        physics
                            .iter()
                            .map(|to| {
                                // Finite, for the checkpoint's JSON: an unsupported
                                // change is refused by `reweightable` anyway.
                                scatterfarm_model::differential::weight_spread(
                                    from,
                                    to,
                                    config.pixel_mm,
                                )
                                .min(f64::MAX)
                            })
                            .collect()
                    })
                    .collect();
                self.refinement = Some(Refinement::with_spread(
                    config,
                    self.config.grid,
                    materials,
                    self.config.seed,
                    last.assignment,
                    reweightable,
                    opaque,
                    spread,
                ));
                self.emit_refinement();
                Ok(())
            }
            _ => {
                self.finish();
                Ok(())
            }
        }
    }

    pub(super) fn finish(&mut self) {
        self.finished = true;
        self.state = None;
        self.pending.clear();
        self.waiting = None;
    }

    /// Makes the refinement's requests pending, or ends the search when it has finished.
    pub(super) fn emit_refinement(&mut self) {
        let Some(r) = self.refinement.as_ref() else {
            self.finish();
            return;
        };
        if r.is_finished() {
            // The refined map is of the grid's pixels, whatever level the coarse stage ended.
            let level = self.config.grid.trailing_zeros();
            let (map, score) = r.current();
            let last = self.levels.last();
            self.refined = Some(LevelResult {
                level,
                assignment: map.to_vec(),
                score: score.or(last.map(|l| l.score)).unwrap_or(0.0),
                permutation: last.map_or(0, |l| l.permutation),
            });
            self.finish();
            return;
        }
        if self.stage_sweep != Some(r.sweep()) {
            self.stage_sweep = Some(r.sweep());
            self.stage_start = self.next_request;
        }
        let requests = r.pending().to_vec();
        self.emit_requests(requests, Waiting::Refine);
    }

    /// The refinement's requests came back.
    pub(super) fn refine_scored(&mut self, scores: &[Score]) -> Result<(), SearchError> {
        let Some(r) = self.refinement.as_mut() else {
            return Err(SearchError::Finished);
        };
        let blocks: Vec<BlockScore> = scores
            .iter()
            .map(|s| BlockScore {
                value: s.value,
                blocks: &s.blocks,
                changes: &s.changes,
            })
            .collect();
        r.submit(&blocks).map_err(SearchError::Refine)?;
        self.emit_refinement();
        Ok(())
    }

    /// Makes `requests` pending, numbered in order.
    pub(super) fn emit_requests(&mut self, requests: Vec<RefineRequest>, waiting: Waiting) {
        self.pending = requests
            .into_iter()
            .map(|r| {
                let index = self.next_request;
                self.next_request += 1;
                RenderRequest {
                    index,
                    seed: r.seed,
                    photons: r.photons,
                    assignment: r.assignment,
                    changes: r.changes,
                }
            })
            .collect();
        self.waiting = Some(waiting);
    }
}
