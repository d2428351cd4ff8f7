//! Exact reuse of MD work: boxes whose state and inputs are bitwise identical are computed once.
//!
//! A box is a deterministic function of its state and the [`BoxWork`]s it is sent (see
//! [`crate::recovery`]). So boxes that start bitwise identical (same content hash of their
//! state, the point id left out) and are sent bitwise identical work stay bitwise identical,
//! and one of them, the class's *representative*, can be stepped for all. The pool keeps, for
//! every box that takes part, the box whose state it has (`rep_of`: itself when its own state
//! is current). A call's work is grouped by (representative, work without the id); one box per
//! group is stepped and its result goes to every member. When a class splits (its members get
//! different work), each new group's stepped box is first given the representative's state of
//! before the call (a snapshot of it restored under the member's id); a member left out of a
//! call whose representative is stepped is given that state too, so no box ever loses the
//! state it stands for.
//!
//! The point id enters a box's future in one place only: energy added to a box with no
//! kinetic energy draws random velocities seeded by (seed, id, step). Work that adds or removes
//! energy is therefore never shared between boxes (its group holds that box alone): reuse is
//! exact by construction, not by tolerance.

use crate::backend::{BoxState, BoxWork, PointId};
use crate::error::MdError;
use crate::ids::IdMap;
use sha2::{Digest, Sha256};
use std::collections::HashMap;

/// SHA-256 of a box's state with its point id left out.
pub fn content_hash(state: &BoxState) -> Result<[u8; 32], MdError> {
    let mut s = state.clone();
    s.meta.id = 0;
    let bytes = serde_json::to_vec(&s).map_err(|e| MdError::invalid("box state", e.to_string()))?;
    Ok(Sha256::digest(&bytes).into())
}

/// The bits of a work item that decide a box's future, the id left out unless the work adds
/// or removes energy (then the id is part of the key: see the module's documentation).
type WorkKey = ([u64; 9], u64, u64, u64, u8, Option<PointId>);

fn work_key(w: &BoxWork) -> WorkKey {
    let mut l = [0u64; 9];
    for i in 0..3 {
        for j in 0..3 {
            l[3 * i + j] = w.velocity_gradient[i][j].to_bits();
        }
    }
    let sampling = match w.stress_sampling {
        crate::StressSampling::Last => 0,
        crate::StressSampling::Average => 1,
    };
    let id = (w.energy_to_add_ev != 0.0).then_some(w.id);
    (l, w.steps, w.dt_ps.to_bits(), w.energy_to_add_ev.to_bits(), sampling, id)
}

/// What one call does under reuse.
#[derive(Debug, Default, PartialEq)]
pub struct Plan {
    /// The work sent to the endpoints: one item per group (and every box not taking part).
    pub physical: Vec<BoxWork>,
    /// For each item of the call's work, the index of its item in `physical`.
    pub source: Vec<usize>,
    /// (from, to): the state of `from` before the call is copied to `to` first.
    pub copies: Vec<(PointId, PointId)>,
    /// (box, representative) after the call.
    pub assign: Vec<(PointId, PointId)>,
}

/// The classes of the boxes that take part in reuse.
#[derive(Debug, Default, Clone)]
pub struct Classes {
    rep_of: IdMap<PointId>,
}

impl Classes {
    /// Whether box `id` takes part.
    pub fn contains(&self, id: PointId) -> bool {
        self.rep_of.contains_key(&id)
    }

    pub fn is_empty(&self) -> bool {
        self.rep_of.is_empty()
    }

    /// The box whose state box `id` has (itself when it does not take part).
    pub fn rep(&self, id: PointId) -> PointId {
        self.rep_of.get(&id).copied().unwrap_or(id)
    }

    /// Number of distinct states among the boxes taking part.
    pub fn class_count(&self) -> usize {
        self.rep_of.iter().filter(|(id, rep)| id == rep).count()
    }

    /// Boxes (other than `rep`) whose state `rep` holds.
    pub fn dependants(&self, rep: PointId) -> Vec<PointId> {
        let mut d: Vec<PointId> = self.rep_of.iter().filter(|(id, r)| **r == rep && **id != rep).map(|(id, _)| *id).collect();
        d.sort_unstable();
        d
    }

    /// Makes the boxes of `hashes` take part, each in the class of the first earlier box of
    /// the same content hash (in the order given); they hold their own current states.
    pub fn join(&mut self, hashes: &[(PointId, [u8; 32])]) {
        let mut first: HashMap<[u8; 32], PointId> = HashMap::new();
        for (id, h) in hashes {
            let rep = *first.entry(*h).or_insert(*id);
            self.rep_of.insert(*id, rep);
        }
    }

    /// Box `id` holds its own state again.
    pub fn detach(&mut self, id: PointId) {
        if let Some(r) = self.rep_of.get_mut(&id) {
            *r = id;
        }
    }

    /// The plan of a call of `work` (ids distinct).
    pub fn plan(&self, work: &[BoxWork]) -> Result<Plan, MdError> {
        let mut plan = Plan { source: vec![0; work.len()], ..Default::default() };
        // Group by (representative, work key); `slot[k]`: the group of item k (None: the box
        // does not take part and is stepped as it is).
        let mut groups: HashMap<(PointId, WorkKey), usize> = HashMap::with_capacity(work.len());
        let mut members: Vec<Vec<usize>> = Vec::new();
        let mut group_rep: Vec<PointId> = Vec::new();
        let mut slot: Vec<Option<usize>> = Vec::with_capacity(work.len());
        let mut seen: IdMap<()> = IdMap::default();
        for (k, w) in work.iter().enumerate() {
            if seen.insert(w.id, ()).is_some() {
                return Err(MdError::invalid("box work", format!("point {} appears twice in one call", w.id)));
            }
            let Some(&rep) = self.rep_of.get(&w.id) else {
                slot.push(None);
                continue;
            };
            let gi = *groups.entry((rep, work_key(w))).or_insert_with(|| {
                members.push(Vec::new());
                group_rep.push(rep);
                members.len() - 1
            });
            members[gi].push(k);
            slot.push(Some(gi));
        }
        // The stepped box of each group: the representative when it is a member, else the
        // group's first member, which is first given the representative's state. Physical
        // items keep the order of the call (a group at its first member).
        let mut stepped_reps: IdMap<()> = IdMap::default();
        let mut phys_of_group = vec![usize::MAX; members.len()];
        for (k, s) in slot.iter().enumerate() {
            let Some(gi) = *s else {
                plan.source[k] = plan.physical.len();
                plan.physical.push(work[k]);
                continue;
            };
            if phys_of_group[gi] == usize::MAX {
                let rep = group_rep[gi];
                let ks = &members[gi];
                let chosen = ks.iter().copied().find(|&m| work[m].id == rep).unwrap_or(ks[0]);
                if work[chosen].id == rep {
                    stepped_reps.insert(rep, ());
                } else {
                    plan.copies.push((rep, work[chosen].id));
                }
                for &m in ks {
                    plan.assign.push((work[m].id, work[chosen].id));
                }
                phys_of_group[gi] = plan.physical.len();
                plan.physical.push(work[chosen]);
            }
            plan.source[k] = phys_of_group[gi];
        }
        // Boxes left out of the call whose representative is stepped keep its state of before.
        if !stepped_reps.is_empty() {
            let mut left_out: Vec<(PointId, PointId)> = self
                .rep_of
                .iter()
                .filter(|(id, rep)| *id != *rep && stepped_reps.contains_key(rep) && !seen.contains_key(id))
                .map(|(id, rep)| (*rep, *id))
                .collect();
            left_out.sort_unstable();
            for (rep, id) in left_out {
                plan.copies.push((rep, id));
                plan.assign.push((id, id));
            }
        }
        Ok(plan)
    }

    /// Records the classes after a call of `plan`.
    pub fn apply(&mut self, plan: &Plan) {
        for (id, rep) in &plan.assign {
            self.rep_of.insert(*id, *rep);
        }
    }
}
