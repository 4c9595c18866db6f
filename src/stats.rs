//! The statistics of success counts: how well an evaluation knows a rate (the Wilson
//! interval) and whether two evaluations differ (Fisher's exact test; McNemar's for
//! episodes paired by scene). Hand-written: closed forms over factorials, not worth a
//! statistics crate and its dependencies.

/// The Wilson score interval (95 %) of a success rate seen as `successes` of `episodes`
/// (None with no episode): unlike the normal approximation it stays inside [0, 1] and is
/// not empty at 0 or all successes, the usual case of a task a policy always or never does.
pub fn wilson_interval(successes: u64, episodes: u64) -> Option<(f64, f64)> {
    if episodes == 0 {
        return None;
    }
    const Z: f64 = 1.959_963_984_540_054;
    let n = episodes as f64;
    let p = successes.min(episodes) as f64 / n;
    let z2 = Z * Z;
    let centre = (p + z2 / (2.0 * n)) / (1.0 + z2 / n);
    let half = Z * (p * (1.0 - p) / n + z2 / (4.0 * n * n)).sqrt() / (1.0 + z2 / n);
    Some(((centre - half).max(0.0), (centre + half).min(1.0)))
}

/// [`wilson_interval`] as a table cell (`11-47 %`; `-` with no episode).
pub fn interval_words(successes: u64, episodes: u64) -> String {
    match wilson_interval(successes, episodes) {
        Some((lo, hi)) => format!("{:.0}-{:.0} %", 100.0 * lo, 100.0 * hi),
        None => "-".into(),
    }
}

/// A success count: `successes` of `episodes`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct Count {
    /// Episodes that succeeded.
    pub successes: u64,
    /// Episodes run.
    pub episodes: u64,
}

impl Count {
    /// The rate in [0, 1]; 0 with no episode.
    pub fn rate(self) -> f64 {
        if self.episodes == 0 {
            0.0
        } else {
            self.successes as f64 / self.episodes as f64
        }
    }
}

/// Fisher's exact test, two-sided, of two success counts: the probability, were both
/// drawn at one rate, of a split of their successes as unlikely as this one or more so
/// (the hypergeometric tables no more probable than the one seen, as R's `fisher.test`
/// sums them). `None` when a count has no episode or more successes than episodes.
pub fn fisher_exact(a: Count, b: Count) -> Option<f64> {
    if a.episodes == 0 || b.episodes == 0 || a.successes > a.episodes || b.successes > b.episodes {
        return None;
    }
    let total = a.episodes + b.episodes;
    let wins = a.successes + b.successes;
    // ln k! for k = 0..=total.
    let mut ln_fact = Vec::with_capacity(total as usize + 1);
    ln_fact.push(0.0f64);
    for k in 1..=total {
        let prev = ln_fact[k as usize - 1];
        ln_fact.push(prev + (k as f64).ln());
    }
    let ln_choose =
        |n: u64, k: u64| ln_fact[n as usize] - ln_fact[k as usize] - ln_fact[(n - k) as usize];
    // P(A has x of the successes), the margins fixed.
    let ln_p = |x: u64| {
        ln_choose(wins, x) + ln_choose(total - wins, a.episodes - x) - ln_choose(total, a.episodes)
    };
    let seen = ln_p(a.successes);
    let low = wins.saturating_sub(b.episodes);
    let high = wins.min(a.episodes);
    // Tables within a relative 1e-7 of the one seen count as equally likely (rounding).
    let p: f64 = (low..=high)
        .map(ln_p)
        .filter(|&l| l <= seen + 1e-7)
        .map(f64::exp)
        .sum();
    Some(p.min(1.0))
}

/// McNemar's exact test, two-sided, of paired outcomes: `only_a` pairs where only the
/// first succeeded, `only_b` where only the second did; the binomial test of the split at
/// one half (pairs both agree on say nothing about a difference). 1 with no disagreement.
pub fn mcnemar_exact(only_a: u64, only_b: u64) -> f64 {
    let n = only_a + only_b;
    let k = only_a.min(only_b);
    // P(X <= k) for X ~ Binomial(n, 1/2), in logs: C(n, i) / 2^n.
    let mut ln_choose = 0.0f64; // ln C(n, 0)
    let mut tail = 0.0f64;
    for i in 0..=k {
        if i > 0 {
            ln_choose += ((n - i + 1) as f64).ln() - (i as f64).ln();
        }
        tail += (ln_choose - n as f64 * std::f64::consts::LN_2).exp();
    }
    (2.0 * tail).min(1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wilson_intervals_match_the_published_values() {
        // Newcombe (1998), "Two-sided confidence intervals for the single proportion",
        // Table I, method 3 (the Wilson score interval), to its four decimals.
        for (k, n, want) in [
            (81, 263, (0.2553, 0.3662)),
            (15, 148, (0.0624, 0.1605)),
            (0, 20, (0.0, 0.1611)),
            (1, 29, (0.0061, 0.1718)),
        ] {
            let (lo, hi) = wilson_interval(k, n).unwrap();
            assert!(
                (lo - want.0).abs() < 5e-5 && (hi - want.1).abs() < 5e-5,
                "{k}/{n}: {lo} {hi}"
            );
        }
        // All successes: the upper end is 1, the lower end below the rate.
        let (lo, hi) = wilson_interval(20, 20).unwrap();
        assert!((lo - 0.8389).abs() < 5e-5 && hi == 1.0, "{lo} {hi}");
        assert_eq!(wilson_interval(0, 0), None);
        assert_eq!(interval_words(5, 20), "11-47 %");
        assert_eq!(interval_words(0, 0), "-");
    }

    fn count(successes: u64, episodes: u64) -> Count {
        Count {
            successes,
            episodes,
        }
    }

    #[test]
    fn fisher_matches_the_textbook_examples() {
        // Fisher's lady tasting tea (R's `fisher.test` example, Agresti 1990): 3 of 4 cups
        // right against 1 of 4, p = 0.4857.
        let p = fisher_exact(count(3, 4), count(1, 4)).unwrap();
        assert!((p - 0.485_714).abs() < 1e-6, "{p}");
        // Wikipedia's "Fisher's exact test" example: 1 of 10 against 11 of 14, p = 0.002759.
        let p = fisher_exact(count(1, 10), count(11, 14)).unwrap();
        assert!((p - 0.002_759).abs() < 1e-6, "{p}");
        // Symmetric in the two counts and in success against failure.
        let q = fisher_exact(count(11, 14), count(1, 10)).unwrap();
        let r = fisher_exact(count(9, 10), count(3, 14)).unwrap();
        assert!(
            (p - q).abs() < 1e-12 && (p - r).abs() < 1e-12,
            "{p} {q} {r}"
        );
        // Equal counts: nothing more likely than the table seen, so p = 1.
        assert!((fisher_exact(count(5, 10), count(5, 10)).unwrap() - 1.0).abs() < 1e-9);
        // All or nothing on both sides: one table only.
        assert!((fisher_exact(count(20, 20), count(20, 20)).unwrap() - 1.0).abs() < 1e-9);
        assert_eq!(fisher_exact(count(0, 0), count(1, 2)), None);
        assert_eq!(fisher_exact(count(3, 2), count(1, 2)), None);
    }

    #[test]
    fn mcnemar_is_the_two_sided_binomial_test_of_the_disagreements() {
        // R: binom.test(1, 10)$p.value = 0.02148438 (= 22 / 1024).
        assert!((mcnemar_exact(1, 9) - 22.0 / 1024.0).abs() < 1e-12);
        assert!((mcnemar_exact(9, 1) - 22.0 / 1024.0).abs() < 1e-12);
        // binom.test(0, 5): 2 / 32.
        assert!((mcnemar_exact(0, 5) - 0.0625).abs() < 1e-12);
        // An even split, or no disagreement at all: nothing to see.
        assert_eq!(mcnemar_exact(4, 4), 1.0);
        assert_eq!(mcnemar_exact(0, 0), 1.0);
        // Many pairs stay finite: binom.test(40, 100)$p.value = 0.05688793.
        assert!((mcnemar_exact(40, 60) - 0.056_887_93).abs() < 1e-7);
    }
}
