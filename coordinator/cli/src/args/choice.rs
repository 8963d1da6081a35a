//! Command-line choices among a library's named values (a metric, a search mode): the
//! libraries name their values and know nothing of clap; this parses those names.

use clap::builder::{PossibleValuesParser, TypedValueParser};
use scatterfarm_job::options::{SearchMode, TiebreakMetric};
use scatterfarm_search::similarity::Metric;

/// A value a flag chooses by name.
pub trait Named: Copy + Send + Sync + 'static {
    /// Every value, in the order `--help` lists them.
    fn all() -> &'static [Self];
    /// Its name on the command line (the job spec's too).
    fn name(self) -> &'static str;
}

impl Named for Metric {
    fn all() -> &'static [Self] {
        &Metric::ALL
    }
    fn name(self) -> &'static str {
        Metric::name(self)
    }
}

impl Named for SearchMode {
    fn all() -> &'static [Self] {
        &SearchMode::ALL
    }
    fn name(self) -> &'static str {
        SearchMode::name(self)
    }
}

impl Named for scatterfarm_search::refine::Screen {
    fn all() -> &'static [Self] {
        &scatterfarm_search::refine::Screen::ALL
    }
    fn name(self) -> &'static str {
        scatterfarm_search::refine::Screen::name(self)
    }
}

impl Named for TiebreakMetric {
    fn all() -> &'static [Self] {
        &TiebreakMetric::ALL
    }
    fn name(self) -> &'static str {
        TiebreakMetric::name(self)
    }
}

/// A value parser for a flag choosing one of `T`'s values by name (clap lists them and refuses
/// any other).
pub fn choice<T: Named>() -> impl TypedValueParser<Value = T> {
    PossibleValuesParser::new(T::all().iter().map(|v| v.name())).map(|name| {
        *T::all()
            .iter()
            .find(|v| v.name() == name)
            .expect("clap accepts only the listed names")
    })
}
