//! Explicit worker threads for one prediction.
//!
//! Inference runs on the caller's thread unless it is given more ([`crate::predict::Policy::set_threads`]):
//! then the work that splits into independent parts (the U-net's neighbour searches, the
//! edge frames and radial bases of each U-net graph, each attention's edges by destination,
//! the per-node layers by runs of nodes, the FiLM hypernetwork by outputs, the translation
//! head's query batches) runs on scoped threads started for that call and joined before it returns,
//! so no thread outlives a call and nothing runs in the background. Every part computes
//! exactly what the single-threaded loop computes for it, in the same order, so the results
//! do not depend on the thread count (tested bit for bit).
//!
//! Stage timings are thread CPU time ([`crate::predict::thread_seconds`]); the CPU time the
//! workers spend is added to a process-wide counter ([`worker_seconds`]) that
//! [`crate::predict::CpuTimer`] includes, so a stage's time stays its whole CPU cost.

use std::ops::Range;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Mutex, PoisonError};

/// Worker CPU time of all finished parts, nanoseconds.
static WORKER_NANOS: AtomicU64 = AtomicU64::new(0);

/// CPU seconds spent so far by worker threads of [`run_parts`] (all threads of the process
/// together; the calling threads' own time is not in it).
pub fn worker_seconds() -> f64 {
    WORKER_NANOS.load(Ordering::Relaxed) as f64 * 1e-9
}

/// `n` items in at most `parts` contiguous ranges of nearly equal length (no empty range;
/// none at all when `n` is 0).
pub fn split_even(n: usize, parts: usize) -> Vec<Range<usize>> {
    let parts = parts.clamp(1, n.max(1));
    (0..parts)
        .map(|p| p * n / parts..(p + 1) * n / parts)
        .filter(|r| !r.is_empty())
        .collect()
}

/// Runs `work` on each of `items` (one per part), the first on the calling thread and each
/// other on a scoped thread of its own; returns the results in order.
///
/// A part that panics propagates its panic to the caller once all parts have finished.
pub fn run_parts<T: Send, R: Send>(items: Vec<T>, work: impl Fn(T) -> R + Sync) -> Vec<R> {
    let mut items = items.into_iter();
    let Some(first) = items.next() else {
        return Vec::new();
    };
    let work = &work;
    std::thread::scope(|s| {
        let handles: Vec<_> = items
            .map(|item| {
                s.spawn(move || {
                    let t0 = crate::predict::thread_seconds();
                    let r = work(item);
                    let ns = ((crate::predict::thread_seconds() - t0).max(0.0) * 1e9) as u64;
                    WORKER_NANOS.fetch_add(ns, Ordering::Relaxed);
                    r
                })
            })
            .collect();
        let mut out = Vec::with_capacity(handles.len() + 1);
        out.push(work(first));
        for h in handles {
            match h.join() {
                Ok(r) => out.push(r),
                Err(p) => std::panic::resume_unwind(p),
            }
        }
        out
    })
}

/// Runs `work` on every item on up to `threads` threads (the caller's and scoped ones,
/// through [`run_parts`]), each thread taking the next item no thread has taken yet, so a
/// thread that finishes early takes more instead of waiting for a fixed share to end;
/// returns the results in item order. Each item runs once, as it would on one thread.
pub fn run_dynamic<T: Send, R: Send>(
    items: Vec<T>,
    threads: usize,
    work: impl Fn(T) -> R + Sync,
) -> Vec<R> {
    let n = items.len();
    let threads = threads.clamp(1, n.max(1));
    if threads < 2 {
        return items.into_iter().map(work).collect();
    }
    // A lock per item and per result, each held only to move a value in or out: the index
    // counter already gives every item to exactly one thread.
    let slots: Vec<Mutex<Option<T>>> = items.into_iter().map(|t| Mutex::new(Some(t))).collect();
    let results: Vec<Mutex<Option<R>>> = (0..n).map(|_| Mutex::new(None)).collect();
    let next = AtomicUsize::new(0);
    run_parts(vec![(); threads], |()| loop {
        let i = next.fetch_add(1, Ordering::Relaxed);
        let Some(slot) = slots.get(i) else {
            break;
        };
        let item = slot.lock().unwrap_or_else(PoisonError::into_inner).take();
        if let Some(item) = item {
            let r = work(item);
            *results[i].lock().unwrap_or_else(PoisonError::into_inner) = Some(r);
        }
    });
    results
        .into_iter()
        .filter_map(|m| m.into_inner().unwrap_or_else(PoisonError::into_inner))
        .collect()
}

/// Runs `f` on at most `parts` contiguous ranges of `0..n` ([`split_even`]; all of it on the
/// calling thread when that is one range) and joins the outputs in order.
pub fn map_ranges<T: Send>(
    n: usize,
    parts: usize,
    f: impl Fn(Range<usize>) -> crate::error::Result<Vec<T>> + Sync,
) -> crate::error::Result<Vec<T>> {
    let ranges = split_even(n, parts);
    if ranges.len() < 2 {
        return f(0..n);
    }
    concat(run_parts(ranges, f))
}

/// Runs `f` on every `chunk`-long slice of `items` (the last may be shorter) on up to
/// `threads` threads, each taking the next chunk not yet taken ([`run_dynamic`]), and joins
/// the outputs in order: the same chunks, so the same outputs, for any thread count.
pub fn map_chunks<T: Sync, R: Send>(
    items: &[T],
    chunk: usize,
    threads: usize,
    f: impl Fn(&[T]) -> crate::error::Result<Vec<R>> + Sync,
) -> crate::error::Result<Vec<R>> {
    let chunks: Vec<&[T]> = items.chunks(chunk.max(1)).collect();
    concat(run_dynamic(chunks, threads, f))
}

/// The parts' outputs joined in order (the first error if any). The first part's buffer is
/// grown in place (a large one is remapped, not copied) and only the others are copied into
/// it: appending every part to a new, growing buffer copied the whole output once or twice
/// more on one thread, and touched fresh pages, after every parallel stage.
fn concat<T>(parts: Vec<crate::error::Result<Vec<T>>>) -> crate::error::Result<Vec<T>> {
    let parts = parts
        .into_iter()
        .collect::<crate::error::Result<Vec<_>>>()?;
    let total = parts.iter().map(Vec::len).sum::<usize>();
    let mut parts = parts.into_iter();
    let mut out = parts.next().unwrap_or_default();
    out.reserve_exact(total - out.len());
    for part in parts {
        out.extend(part);
    }
    Ok(out)
}

/// Applies the row-wise `f` (rows of `row` values in, rows out) to runs of whole rows of `x`
/// on up to `threads` threads, each with at least `min_rows` rows, and joins the outputs in
/// order: what `f(x)` gives, for an `f` that treats every row on its own.
pub fn map_rows(
    x: &[f32],
    row: usize,
    (threads, min_rows): (usize, usize),
    f: impl Fn(&[f32]) -> crate::error::Result<Vec<f32>> + Sync,
) -> crate::error::Result<Vec<f32>> {
    let rows = crate::layers::rows_of("row-wise input", x.len(), row.max(1))?;
    map_ranges(rows, threads.min(rows / min_rows.max(1)), |r| {
        f(&x[r.start * row..r.end * row])
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn even_splits_cover_the_items_once() {
        for n in [0, 1, 2, 7, 100] {
            for parts in [1, 2, 3, 8, 200] {
                let r = split_even(n, parts);
                assert!(r.len() <= parts.max(1));
                assert!(r.iter().all(|r| !r.is_empty()));
                let flat: Vec<usize> = r.into_iter().flatten().collect();
                assert_eq!(flat, (0..n).collect::<Vec<_>>(), "n {n} parts {parts}");
            }
        }
    }

    #[test]
    fn parts_run_in_order_and_count_worker_time() {
        let before = worker_seconds();
        let out = run_parts((0..4u64).collect(), |i| {
            // Enough work for the workers' CPU time to register.
            (0..200_000u64).fold(i, |a, x| a.wrapping_mul(31).wrapping_add(x))
        });
        let want: Vec<u64> = (0..4u64)
            .map(|i| (0..200_000u64).fold(i, |a, x| a.wrapping_mul(31).wrapping_add(x)))
            .collect();
        assert_eq!(out, want);
        assert!(
            worker_seconds() > before,
            "the three workers' CPU time is counted"
        );
        assert!(run_parts(Vec::<u8>::new(), |x| x).is_empty());
    }

    #[test]
    fn dynamic_runs_give_every_item_once_in_order() {
        let ran = AtomicUsize::new(0);
        for threads in [1, 2, 3, 16] {
            // Uneven items: the threads take different numbers of them.
            let out = run_dynamic((0..37u64).collect(), threads, |i| {
                ran.fetch_add(1, Ordering::Relaxed);
                (0..(i % 5) * 20_000).fold(i, |a, x| a.wrapping_mul(31).wrapping_add(x))
            });
            let want: Vec<u64> = (0..37u64)
                .map(|i| (0..(i % 5) * 20_000).fold(i, |a, x| a.wrapping_mul(31).wrapping_add(x)))
                .collect();
            assert_eq!(out, want, "{threads} threads");
        }
        assert_eq!(
            ran.load(Ordering::Relaxed),
            4 * 37,
            "each item ran once per call"
        );
        assert!(run_dynamic(Vec::<u8>::new(), 2, |x| x).is_empty());
    }

    #[test]
    fn chunk_maps_see_the_same_chunks_for_any_thread_count() {
        let items: Vec<u32> = (0..23).collect();
        // Each chunk's output names the chunk it saw.
        let f = |c: &[u32]| Ok(vec![(c[0], c.len())]);
        let want: Vec<(u32, usize)> = (0..6).map(|i| (4 * i, if i < 5 { 4 } else { 3 })).collect();
        for threads in [1, 2, 3, 8] {
            assert_eq!(map_chunks(&items, 4, threads, f).unwrap(), want);
        }
        assert!(map_chunks(&items[..0], 4, 2, f).unwrap().is_empty());
    }

    #[test]
    fn row_maps_join_in_order_and_pass_errors_on() {
        let x: Vec<f32> = (0..40).map(|v| v as f32).collect();
        let double = |r: &[f32]| Ok(r.iter().map(|v| 2.0 * v).collect());
        let want: Vec<f32> = x.iter().map(|v| 2.0 * v).collect();
        for threads in [1, 2, 3, 7] {
            assert_eq!(map_rows(&x, 4, (threads, 2), double).unwrap(), want);
        }
        let failing = |r: &[f32]| {
            if r.contains(&39.0) {
                Err(crate::PolicyError::ShapeMismatch {
                    name: "last row".into(),
                    expected: vec![],
                    got: vec![],
                })
            } else {
                Ok(r.to_vec())
            }
        };
        assert!(map_rows(&x, 4, (3, 1), failing).is_err());
        assert!(
            map_rows(&x[..7], 4, (2, 1), double).is_err(),
            "a partial row"
        );
    }
}
