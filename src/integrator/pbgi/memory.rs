//! PBGI's state under a memory budget: its per-pixel tables and its records, their bytes,
//! and the checks that they fit the budget's share for the integrator's state.

use super::pixel_reuse::{Gathered, SURFACES_PER_PIXEL};
use super::{radiance_cache, IrradianceCache, PbgiIntegrator};
use crate::units::{format_size, whole_mib};
use anyhow::{bail, Result};
use std::sync::atomic::AtomicBool;
use std::sync::{Mutex, PoisonError};

impl PbgiIntegrator {
    /// Bytes held now.
    pub(super) fn state_bytes_now(&self) -> u64 {
        let kept: usize = self
            .gathered
            .iter()
            .map(|m| m.lock().unwrap_or_else(PoisonError::into_inner).capacity())
            .sum();
        let slots = self.gathered.len() * size_of::<Mutex<Vec<Gathered>>>();
        let bytes = (slots + kept * size_of::<Gathered>()) as u64 + self.record_bytes();
        bytes + self.edge.bytes() + self.split.bytes()
    }

    /// The irradiance and radiance caches' records.
    fn record_bytes(&self) -> u64 {
        let irradiance = self.irradiance_cache.as_ref();
        let radiance = self.radiance_cache.as_ref();
        irradiance.map_or(0, IrradianceCache::bytes)
            + radiance.map_or(0, radiance_cache::RadianceCache::bytes)
    }

    /// The per-pixel tables at their largest with `surfaces` kept per pixel: every pixel's
    /// gathers on as many surfaces, the splits' and edge rays' tables, and the cache's
    /// per-pixel flags and probe order.
    fn table_bytes_with(&self, surfaces: usize) -> u64 {
        let pixels = self.window_pixels() as u64;
        let gathered = match self.settings.reuse > 1 {
            true => size_of::<Mutex<Vec<Gathered>>>() + surfaces * size_of::<Gathered>(),
            false => 0,
        };
        let cache = match self.settings.cache > 0.0 {
            true => size_of::<AtomicBool>() + size_of::<[u32; 2]>(),
            false => 0,
        };
        pixels * (gathered + cache) as u64 + self.edge.bytes() + self.split.bytes()
    }

    fn table_bytes_most(&self) -> u64 {
        self.table_bytes_with(self.surfaces_per_pixel)
    }

    /// Under a budget, keeps as many surfaces per pixel (up to `SURFACES_PER_PIXEL`) as
    /// let the per-pixel tables at their largest take at most three quarters of the state's
    /// share, the rest left for records; refuses, before the bake, a window whose tables do
    /// not fit with one. A sample on a surface its pixel does not keep gathers for itself.
    pub(super) fn fit_tables(&mut self) -> Result<()> {
        let Some(cap) = self.state_cap else {
            return Ok(());
        };
        let room = cap / 4 * 3;
        let fits = (1..=SURFACES_PER_PIXEL)
            .rev()
            .find(|&s| self.table_bytes_with(s) <= room);
        let Some(surfaces) = fits else {
            let [x0, x1, y0, y1] = self.window;
            let least = self.table_bytes_with(1);
            bail!(
                "pbgi's per-pixel tables for a {}x{} window take at least {}, more than three \
                 quarters of the {} that --mem-budget keeps for the integrator's state (a \
                 quarter): a budget of at least {} fits, or render the frame in tiles with \
                 --crop",
                x1 - x0,
                y1 - y0,
                format_size(least),
                format_size(cap),
                format_size(whole_mib(least.div_ceil(3) * 16))
            );
        };
        self.surfaces_per_pixel = surfaces;
        Ok(())
    }

    /// How many of `items`, taken in order at `cost` bytes each, still fit the budget's
    /// share beside `held` bytes of a cache being built, the caches in place and the
    /// per-pixel tables at their largest: all of them without a budget.
    pub(super) fn records_that_fit<T>(
        &self,
        held: u64,
        items: &[T],
        cost: impl Fn(&T) -> u64,
    ) -> usize {
        let Some(cap) = self.state_cap else {
            return items.len();
        };
        let room = cap.saturating_sub(self.record_bytes() + self.table_bytes_most());
        let mut more = held;
        items
            .iter()
            .take_while(|t| {
                more += cost(t);
                more <= room
            })
            .count()
    }
}
