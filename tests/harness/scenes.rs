//! The scene texts and job files the tests use, written once.

/// A 4 × 4 scene with its own size and a material of its own (fog), for `render` and `show`.
pub const SMALL: &str = r##"
[geometry]
size_mm = 16.0
grid = 4
positions = 16
directions = 3

[materials]
fog = { sigma_s = 0.3, sigma_a = 0.02, g = 0.1 }

[map]
legend = { "." = "moderate", "#" = "opaque", "f" = "fog" }
rows = [
  "....",
  ".#f.",
  ".ff.",
  "....",
]
"##;

/// Two materials at grid 4, 16 positions × 3 directions.
pub const TWO: &str = r##"
[geometry]
grid = 4
positions = 16
directions = 3
[map]
legend = { "." = "moderate", "#" = "opaque" }
rows = ["....", ".##.", ".##.", "...."]
"##;

/// Three materials at grid 4, 16 positions × 3 directions: the farm's job's scene
/// (`three.toml`).
pub const THREE: &str = r##"
[geometry]
grid = 4
positions = 16
directions = 3
[map]
legend = { "." = "moderate", "o" = "opaque", "b" = "back" }
rows = ["oo..", "oo..", "...b", "..bb"]
"##;

/// The farm job's keys besides its scene: a job file writes them as they are, `reconstruct` as
/// flags.
pub const JOB_KEYS: [(&str, &str); 4] = [
    ("permutations", "2"),
    ("iterations", "4"),
    ("photons_per_iteration", "256"),
    ("seed", "7"),
];

/// Which search a job runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Search {
    Paper,
    Fast,
    /// The likelihood search whose refinement screens by differential renders.
    Differential,
}

impl Search {
    /// Its name in job files and flags.
    pub fn name(self) -> &'static str {
        match self {
            Search::Paper => "paper",
            Search::Fast => "fast",
            Search::Differential => "likelihood",
        }
    }

    /// The job keys it sets besides [`JOB_KEYS`] and `search`.
    pub fn keys(self) -> &'static [(&'static str, &'static str)] {
        match self {
            Search::Paper | Search::Fast => &[],
            // The sweeps at the nominal 4 × 256 photons, small enough for a test.
            Search::Differential => &[
                ("refine_screen", "differential"),
                ("refine_sweeps", "3"),
                ("refine_photons", "1024"),
                ("refine_confirm_photons", "2048"),
                ("refine_direct_photons", "1024"),
            ],
        }
    }
}

/// The job file with the paper's search: `scene` on line 1, then [`JOB_KEYS`] on lines 2 to 5,
/// then `search` on line 6.
pub fn job_toml() -> String {
    job_toml_of(Search::Paper)
}

/// The job file of `search`. The faster search has every option on by default
/// (racing, re-scoring, early step 2, common random numbers, the tiebreak).
pub fn job_toml_of(search: Search) -> String {
    let mut text = "scene = \"three.toml\"\n".to_string();
    for (key, value) in JOB_KEYS {
        text.push_str(&format!("{key} = {value}\n"));
    }
    text.push_str(&format!("search = \"{}\"\n", search.name()));
    for (key, value) in search.keys() {
        let value = value
            .parse::<f64>()
            .map_or_else(|_| format!("\"{value}\""), |_| value.to_string());
        text.push_str(&format!("{key} = {value}\n"));
    }
    text
}

/// A job long enough to still run while a page is loaded.
pub const LONG_DEMO_JOB: &str = "scene = \"demo8\"\npermutations = 4\niterations = 8\nphotons_per_iteration = 512\nname = \"page-test-job\"\n";
