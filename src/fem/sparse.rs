//! A symmetric sparse pattern in compressed-column form (both triangles stored) shared
//! by all affine terms, so that K(p) = Σ cᵢ Kᵢ is a weighted sum of value arrays and the
//! symbolic Cholesky analysis is done once per model.

use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};

/// Zeros between two nonzeros of a term that [`Pattern::nonzero_runs`] keeps in one run.
pub const RUN_GAP: usize = 16;

/// Compressed-column pattern of an `n × n` symmetric matrix, rows sorted per column.
#[derive(Clone, Debug)]
pub struct Pattern {
    pub n: usize,
    pub col_ptr: Vec<usize>,
    pub row_idx: Vec<usize>,
    pub symbolic: SymbolicSparseColMat<usize>,
}

impl Pattern {
    /// Pattern holding every `(row, col)` of `entries` (duplicates merged).
    pub fn from_entries(n: usize, entries: impl Iterator<Item = (usize, usize)>) -> Pattern {
        let mut cols: Vec<Vec<usize>> = vec![Vec::new(); n];
        for (r, c) in entries {
            cols[c].push(r);
        }
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::new();
        col_ptr.push(0);
        for mut rows in cols {
            rows.sort_unstable();
            rows.dedup();
            row_idx.extend_from_slice(&rows);
            col_ptr.push(row_idx.len());
        }
        let symbolic =
            SymbolicSparseColMat::new_checked(n, n, col_ptr.clone(), None, row_idx.clone());
        Pattern {
            n,
            col_ptr,
            row_idx,
            symbolic,
        }
    }

    /// Position of entry (r, c) in the value array. Callers only ask for entries that
    /// were put in the pattern; a miss is a programming error inside this module.
    pub fn index(&self, r: usize, c: usize) -> usize {
        let (s, e) = (self.col_ptr[c], self.col_ptr[c + 1]);
        match self.row_idx[s..e].binary_search(&r) {
            Ok(k) => s + k,
            Err(_) => unreachable!("entry ({r}, {c}) not in the sparse pattern"),
        }
    }

    /// y = A x for the full symmetric matrix with values `val`.
    pub fn matvec(&self, val: &[f64], x: &[f64], y: &mut [f64]) {
        y.iter_mut().for_each(|v| *v = 0.0);
        for c in 0..self.n {
            let xc = x[c];
            if xc == 0.0 {
                continue;
            }
            for p in self.col_ptr[c]..self.col_ptr[c + 1] {
                y[self.row_idx[p]] += val[p] * xc;
            }
        }
    }

    /// Y = A X for the full symmetric matrix with values `val`, X and Y row-major n × w
    /// (row i's w entries contiguous). One pass over the pattern for all w columns, where
    /// w [`Self::matvec`]s read it w times: projecting 47 affine terms on an 80-vector basis
    /// was memory-bound on the pattern. Entries of `val` that are zero (a term local to a
    /// joint or a copper region stores the whole pattern) are skipped. Each y entry sums
    /// its terms in the order `matvec` does, so the column products are the same numbers.
    pub fn matmat_rows(&self, val: &[f64], x: &[f64], w: usize, y: &mut [f64]) {
        y.iter_mut().for_each(|v| *v = 0.0);
        if w == 0 {
            return;
        }
        for c in 0..self.n {
            let xc = &x[c * w..(c + 1) * w];
            for p in self.col_ptr[c]..self.col_ptr[c + 1] {
                let v = val[p];
                if v == 0.0 {
                    continue;
                }
                let r = self.row_idx[p];
                y[r * w..(r + 1) * w]
                    .iter_mut()
                    .zip(xc)
                    .for_each(|(o, xv)| *o += v * xv);
            }
        }
    }

    /// xᵀ A x for the full symmetric matrix with values `val`: a gather over the pattern,
    /// no product vector.
    pub fn quadratic_form(&self, val: &[f64], x: &[f64]) -> f64 {
        let mut s = 0.0;
        for (c, &xc) in x.iter().enumerate().take(self.n) {
            if xc == 0.0 {
                continue;
            }
            let range = self.col_ptr[c]..self.col_ptr[c + 1];
            let col: f64 = self.row_idx[range.clone()]
                .iter()
                .zip(&val[range])
                .map(|(&r, v)| v * x[r])
                .sum();
            s += xc * col;
        }
        s
    }

    /// faer view of the matrix with values `val`.
    pub fn view<'a>(&'a self, val: &'a [f64]) -> SparseColMatRef<'a, usize, f64> {
        SparseColMatRef::new(self.symbolic.as_ref(), val)
    }

    /// The runs [start, end) of `vals` outside which every value is zero; gaps shorter
    /// than [`RUN_GAP`] are kept inside a run (a run's bookkeeping costs more than a few
    /// zeros).
    pub fn nonzero_runs(vals: &[f64]) -> Vec<(usize, usize)> {
        let mut runs: Vec<(usize, usize)> = Vec::new();
        for (i, v) in vals.iter().enumerate() {
            if *v == 0.0 {
                continue;
            }
            match runs.last_mut() {
                Some(last) if i - last.1 < RUN_GAP => last.1 = i + 1,
                _ => runs.push((i, i + 1)),
            }
        }
        runs
    }

    /// [`Self::combine`] over each term's [`Self::nonzero_runs`] only: the same sums in the
    /// same order (the values skipped are zeros), so the same numbers.
    pub fn combine_runs(
        &self,
        coefs: &[f64],
        terms: &[Vec<f64>],
        runs: &[Vec<(usize, usize)>],
    ) -> Vec<f64> {
        let mut out = vec![0.0; self.row_idx.len()];
        for ((c, t), rs) in coefs.iter().zip(terms).zip(runs) {
            if *c == 0.0 {
                continue;
            }
            for &(a, b) in rs {
                for (o, v) in out[a..b].iter_mut().zip(&t[a..b]) {
                    *o += c * v;
                }
            }
        }
        out
    }

    /// Σ cᵢ valsᵢ.
    pub fn combine(&self, coefs: &[f64], terms: &[Vec<f64>]) -> Vec<f64> {
        let mut out = vec![0.0; self.row_idx.len()];
        for (c, t) in coefs.iter().zip(terms) {
            if *c == 0.0 {
                continue;
            }
            for (o, v) in out.iter_mut().zip(t) {
                *o += c * v;
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    #[test]
    fn combining_over_the_nonzero_runs_is_combining_everything() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let n = 30;
        let pat = Pattern::from_entries(
            n,
            (0..n).flat_map(|i| [(i, i), (i, (i + 1) % n), ((i + 1) % n, i)]),
        );
        let len = pat.row_idx.len();
        // A dense term, a term nonzero in two patches, and an all-zero one.
        let dense: Vec<f64> = (0..len).map(|_| rng.random_range(-1.0..1.0)).collect();
        let patch: Vec<f64> = (0..len)
            .map(|i| {
                if (5..9).contains(&i) || (40..70).contains(&i) {
                    rng.random_range(-1.0..1.0)
                } else {
                    0.0
                }
            })
            .collect();
        let terms = vec![dense, patch, vec![0.0; len]];
        let runs: Vec<_> = terms.iter().map(|t| Pattern::nonzero_runs(t)).collect();
        assert_eq!(runs[0], vec![(0, len)]);
        assert_eq!(runs[1], vec![(5, 9), (40, 70)]);
        assert!(runs[2].is_empty());
        let coefs = [0.7, -1.3, 2.0];
        let a = pat.combine_runs(&coefs, &terms, &runs);
        let b = pat.combine(&coefs, &terms);
        assert!(a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()));
    }

    #[test]
    fn the_multi_column_product_is_the_column_products() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let n = 40;
        let entries: Vec<(usize, usize)> = (0..200)
            .map(|_| (rng.random_range(0..n), rng.random_range(0..n)))
            .flat_map(|(r, c)| [(r, c), (c, r)])
            .chain((0..n).map(|i| (i, i)))
            .collect();
        let pat = Pattern::from_entries(n, entries.into_iter());
        // A third of the values zero, as a term local to one region stores them.
        let val: Vec<f64> = (0..pat.row_idx.len())
            .map(|_| {
                if rng.random_range(0..3) == 0 {
                    0.0
                } else {
                    rng.random_range(-1.0..1.0)
                }
            })
            .collect();
        let w = 5;
        let x: Vec<f64> = (0..n * w).map(|_| rng.random_range(-1.0..1.0)).collect();
        let mut y = vec![f64::NAN; n * w];
        pat.matmat_rows(&val, &x, w, &mut y);
        for j in 0..w {
            let xj: Vec<f64> = (0..n).map(|i| x[i * w + j]).collect();
            let mut yj = vec![0.0; n];
            pat.matvec(&val, &xj, &mut yj);
            for i in 0..n {
                assert_eq!(y[i * w + j].to_bits(), yj[i].to_bits(), "({i}, {j})");
            }
        }
    }
}
