//! The AERO simulator (`aero-sim`) as a [`Plant`], in process.

use aero_sim::{AeroParams, AeroSim, CHANNELS};

use crate::{Plant, PlantError};

/// The AERO simulator as a [`Plant`].
pub struct AeroPlant {
    sim: AeroSim,
}

impl AeroPlant {
    /// A simulated AERO.
    pub fn new(params: AeroParams, seed: u64) -> Result<Self, PlantError> {
        Ok(Self {
            sim: AeroSim::new(params, seed)?,
        })
    }

    /// The simulator (for its true state).
    pub fn sim(&self) -> &AeroSim {
        &self.sim
    }
}

fn pair(v: &[f64]) -> [f64; 2] {
    [
        v.first().copied().unwrap_or(0.0),
        v.get(1).copied().unwrap_or(0.0),
    ]
}

impl Plant for AeroPlant {
    fn channels(&self) -> usize {
        CHANNELS
    }
    fn read(&mut self) -> Result<Vec<f64>, PlantError> {
        Ok(self.sim.measure().to_vec())
    }
    fn write(&mut self, v: &[f64]) -> Result<Vec<f64>, PlantError> {
        Ok(self.sim.apply(pair(v)).to_vec())
    }
    fn advance(&mut self, dt: f64) -> Result<(), PlantError> {
        self.sim.advance(dt);
        Ok(())
    }
    fn stop(&mut self) -> Result<(), PlantError> {
        self.sim.apply([0.0, 0.0]);
        Ok(())
    }
    fn limit_hits(&self) -> usize {
        self.sim.stop_hits()
    }
    fn truth(&self) -> Option<Vec<f64>> {
        Some(self.sim.truth().to_vec())
    }
}
