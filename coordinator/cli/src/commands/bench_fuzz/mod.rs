//! `scatterfarm bench fuzz`: every parser of untrusted input (scene TOML, job file and its plan,
//! NPY and sidecar, stored job records with progress and scores, task and result messages, the
//! token file, bounds) driven with generated and mutated inputs, each call under
//! `catch_unwind`. Reports per parser the inputs run, accepted, refused, panics (with the first
//! panic's message and input) and the peak RSS while it ran (`VmHWM`, reset per parser through
//! `/proc/self/clear_refs`), as JSON. The stable toolchain has no coverage-guided fuzzer, so
//! inputs come from [`mutate`]: valid seeds, structure-aware generators and byte- and
//! text-level mutations, all deterministic from `--seed`.

pub mod mutate;
pub mod targets;

use anyhow::{Context, Result};
use clap::Args;
use mutate::Mutator;
use serde::Serialize;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::PathBuf;
use std::sync::Mutex;
use std::time::Instant;

#[derive(Debug, Args)]
pub struct FuzzArgs {
    /// Inputs per parser.
    #[arg(long, default_value_t = 100_000)]
    pub inputs: u64,
    /// The generator's seed: the same seed runs the same inputs.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Only these parsers (comma-separated; default: all of them).
    #[arg(long, value_delimiter = ',')]
    pub parsers: Option<Vec<String>>,
    /// Also write the JSON here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Write the first panicking input and the slowest input of each parser into this folder
    /// (one file per part; the slowest as `slowest-PARSER.N`).
    #[arg(long)]
    pub keep_panics: Option<PathBuf>,
}

/// What one parser did.
#[derive(Debug, Clone, Serialize)]
pub struct ParserReport {
    pub parser: &'static str,
    pub inputs: u64,
    pub accepted: u64,
    pub refused: u64,
    pub panics: u64,
    /// The first panic's message.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub first_panic: Option<String>,
    /// The first panicking input's parts, when kept.
    #[serde(skip)]
    pub first_panic_input: Option<Vec<Vec<u8>>>,
    /// Peak resident memory while this parser ran, KiB (`VmHWM`).
    pub peak_rss_kib: Option<u64>,
    pub seconds: f64,
    /// The slowest input's seconds, and its index in the run (the same seed runs it again).
    pub slowest_seconds: f64,
    pub slowest_index: u64,
    /// The slowest input's parts, when kept.
    #[serde(skip)]
    pub slowest_input: Option<Vec<Vec<u8>>>,
}

/// The whole run.
#[derive(Debug, Clone, Serialize)]
pub struct FuzzReport {
    pub seed: u64,
    pub inputs_per_parser: u64,
    pub parsers: Vec<ParserReport>,
}

/// The message of the latest panic, from the hook.
static LAST_PANIC: Mutex<Option<String>> = Mutex::new(None);

thread_local! {
    /// Whether a parser runs now: the hook is quiet only then.
    static IN_PARSER: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// `VmHWM` of this process, KiB.
fn peak_rss_kib() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// Resets `VmHWM` to the current RSS (Linux: `5` to `/proc/self/clear_refs`).
fn reset_peak_rss() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

/// Runs `inputs` inputs through `target`; panics are caught and counted.
pub fn fuzz_one(target: &targets::Target, inputs: u64, seed: u64) -> ParserReport {
    let mut m = Mutator::new(seed ^ fnv(target.name));
    let started = Instant::now();
    reset_peak_rss();
    let mut report = ParserReport {
        parser: target.name,
        inputs: 0,
        accepted: 0,
        refused: 0,
        panics: 0,
        first_panic: None,
        first_panic_input: None,
        peak_rss_kib: None,
        seconds: 0.0,
        slowest_seconds: 0.0,
        slowest_index: 0,
        slowest_input: None,
    };
    for i in 0..inputs {
        // The seeds as they are first, then generated and mutated inputs.
        let input = if (i as usize) < target.seeds.len() {
            target.seeds[i as usize].clone()
        } else {
            match (target.generate, m.below(4)) {
                (Some(generate), 0) => {
                    let fresh = generate(&mut m);
                    if m.chance(2) {
                        m.mutate(&fresh, &target.seeds)
                    } else {
                        fresh
                    }
                }
                _ => {
                    let base = m.pick(&target.seeds).clone();
                    m.mutate(&base, &target.seeds)
                }
            }
        };
        report.inputs += 1;
        if i > 0 && i % 100_000 == 0 {
            eprintln!(
                "{:<12} {i} inputs, {:.1} s so far (slowest: #{}, {:.3} s)",
                target.name,
                started.elapsed().as_secs_f64(),
                report.slowest_index,
                report.slowest_seconds
            );
        }
        IN_PARSER.with(|p| p.set(true));
        let one = Instant::now();
        let outcome = catch_unwind(AssertUnwindSafe(|| (target.run)(&input)));
        let took = one.elapsed().as_secs_f64();
        IN_PARSER.with(|p| p.set(false));
        if took > report.slowest_seconds {
            report.slowest_seconds = took;
            report.slowest_index = i;
            report.slowest_input = Some(input.clone());
        }
        match outcome {
            Ok(true) => report.accepted += 1,
            Ok(false) => report.refused += 1,
            Err(_) => {
                report.panics += 1;
                if report.first_panic.is_none() {
                    let message = LAST_PANIC
                        .lock()
                        .map(|mut m| m.take())
                        .unwrap_or_else(|e| e.into_inner().take());
                    report.first_panic = Some(message.unwrap_or_else(|| "a panic".into()));
                    report.first_panic_input = Some(input);
                }
            }
        }
    }
    report.peak_rss_kib = peak_rss_kib();
    report.seconds = started.elapsed().as_secs_f64();
    report
}

/// FNV-1a of a name: each parser gets its own stream from one seed.
fn fnv(name: &str) -> u64 {
    name.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

/// Fuzzes the chosen parsers with panics caught quietly (the hook only records the message).
pub fn fuzz(inputs: u64, seed: u64, only: Option<&[String]>) -> Result<FuzzReport> {
    let all = targets::all();
    if let Some(only) = only {
        for name in only {
            anyhow::ensure!(
                all.iter().any(|t| t.name == name),
                "no parser {name:?} (parsers: {})",
                all.iter().map(|t| t.name).collect::<Vec<_>>().join(", ")
            );
        }
    }
    let previous = std::panic::take_hook();
    std::panic::set_hook(Box::new(|info| {
        let at = info
            .location()
            .map(|l| format!(" at {}:{}", l.file(), l.line()))
            .unwrap_or_default();
        let payload = info
            .payload()
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| info.payload().downcast_ref::<String>().cloned())
            .unwrap_or_default();
        if !IN_PARSER.with(|p| p.get()) {
            eprintln!("the fuzzer itself panicked: {payload}{at}");
        }
        if let Ok(mut last) = LAST_PANIC.lock() {
            *last = Some(format!("{payload}{at}"));
        }
    }));
    let mut parsers = Vec::new();
    for target in all
        .iter()
        .filter(|t| only.is_none_or(|o| o.iter().any(|n| n == t.name)))
    {
        let r = fuzz_one(target, inputs, seed);
        eprintln!(
            "{:<12} {} inputs: {} accepted, {} refused, {} panics, peak RSS {} KiB, {:.1} s \
             (slowest input: #{}, {:.3} s)",
            r.parser,
            r.inputs,
            r.accepted,
            r.refused,
            r.panics,
            r.peak_rss_kib.unwrap_or(0),
            r.seconds,
            r.slowest_index,
            r.slowest_seconds
        );
        parsers.push(r);
    }
    std::panic::set_hook(previous);
    Ok(FuzzReport {
        seed,
        inputs_per_parser: inputs,
        parsers,
    })
}

pub fn run(args: FuzzArgs) -> Result<()> {
    let report = fuzz(args.inputs, args.seed, args.parsers.as_deref())?;
    if let Some(dir) = &args.keep_panics {
        for r in &report.parsers {
            let kept = [("", &r.first_panic_input), ("slowest-", &r.slowest_input)];
            for (prefix, input) in kept {
                for (i, part) in input.iter().flatten().enumerate() {
                    std::fs::create_dir_all(dir)
                        .with_context(|| format!("cannot create {}", dir.display()))?;
                    let path = dir.join(format!("{prefix}{}.{i}", r.parser));
                    std::fs::write(&path, part)
                        .with_context(|| format!("cannot write {}", path.display()))?;
                }
            }
        }
    }
    let text = serde_json::to_string_pretty(&report)?;
    println!("{text}");
    if let Some(out) = &args.out {
        std::fs::write(out, format!("{text}\n"))
            .with_context(|| format!("cannot write {}", out.display()))?;
    }
    let panics: u64 = report.parsers.iter().map(|r| r.panics).sum();
    anyhow::ensure!(panics == 0, "{panics} inputs made a parser panic");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The CI pass: a short run of every parser, no panic.
    #[test]
    fn a_short_pass_of_every_parser_does_not_panic() {
        let report = fuzz(2_000, 1, None).unwrap();
        assert_eq!(report.parsers.len(), targets::all().len());
        for r in &report.parsers {
            assert_eq!(r.inputs, 2_000);
            assert_eq!(r.panics, 0, "{}: {:?}", r.parser, r.first_panic);
            assert!(r.accepted > 0, "{}: no input accepted", r.parser);
            assert!(r.refused > 0, "{}: no input refused", r.parser);
        }
    }
}
