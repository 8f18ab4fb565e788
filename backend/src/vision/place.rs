//! Place recognition over keyframes: a bag of binary words whose vocabulary is learned from the
//! map's own ORB descriptors when the map is built (no external vocabulary file).
//!
//! The vocabulary is a two-level tree of binary centres (k-majority clustering: assignment by
//! Hamming distance, centres by per-bit majority), so quantizing a descriptor costs
//! `2 × branching` distance computations. Every keyframe becomes a TF-IDF weighted, L1
//! normalized word histogram; a query is scored against the keyframes sharing at least one word
//! through an inverted index with the L1 score `1 − ½‖v/‖v‖₁ − w/‖w‖₁‖₁` (1 = identical).
//!
//! The vocabulary and the inverse document frequencies are stored in the map (schema 2);
//! keyframe histograms are recomputed from the stored keyframe descriptors on load. Everything
//! is deterministic: fixed initialization, fixed iteration count, ties to the lower index.

use serde::{Deserialize, Serialize};

use crate::vision::features::Descriptor;

/// Children per tree node: 32 × 32 = 1 024 words, enough for maps of a few hundred keyframes.
pub const VOCABULARY_BRANCHING: usize = 32;
/// k-majority iterations: assignments stop changing after a handful on ORB descriptors.
const KMAJORITY_ITERATIONS: usize = 6;

/// One first-level node: its centre and its children's centres (the words).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VocabularyNode {
    /// First-level centre.
    pub centre: Descriptor,
    /// Word centres under this node.
    pub words: Vec<Descriptor>,
}

/// A two-level binary vocabulary with inverse document frequencies.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Vocabulary {
    /// First-level nodes.
    pub nodes: Vec<VocabularyNode>,
    /// Inverse document frequency per word (word ids count through the nodes in order).
    pub idf: Vec<f64>,
}

/// Index of the nearest descriptor (ties: lower index).
fn nearest(d: &Descriptor, centres: &[Descriptor]) -> usize {
    let mut best = (u32::MAX, 0);
    for (i, c) in centres.iter().enumerate() {
        let dist = d.distance(c);
        if dist < best.0 {
            best = (dist, i);
        }
    }
    best.1
}

/// Per-bit majority of a set of descriptors (ties give 0).
fn majority(members: &[&Descriptor]) -> Descriptor {
    let mut counts = [0u32; 256];
    for d in members {
        for (w, word) in d.0.iter().enumerate() {
            let mut x = *word;
            while x != 0 {
                let b = x.trailing_zeros() as usize;
                counts[64 * w + b] += 1;
                x &= x - 1;
            }
        }
    }
    let half = members.len() as u32;
    let mut out = [0u64; 4];
    for (i, &c) in counts.iter().enumerate() {
        if 2 * c > half {
            out[i / 64] |= 1 << (i % 64);
        }
    }
    Descriptor(out)
}

/// k-majority clustering with evenly spaced initial centres; returns the centres (at most `k`,
/// fewer when there are fewer distinct inputs).
fn kmajority(data: &[&Descriptor], k: usize) -> Vec<Descriptor> {
    if data.is_empty() {
        return Vec::new();
    }
    let mut centres: Vec<Descriptor> = Vec::with_capacity(k);
    let n = data.len();
    for i in 0..k.min(n) {
        let d = *data[i * n / k.min(n)];
        if !centres.contains(&d) {
            centres.push(d);
        }
    }
    let mut assign = vec![0usize; n];
    for _ in 0..KMAJORITY_ITERATIONS {
        for (a, d) in assign.iter_mut().zip(data) {
            *a = nearest(d, &centres);
        }
        for (c, centre) in centres.iter_mut().enumerate() {
            let members: Vec<&Descriptor> = data
                .iter()
                .zip(&assign)
                .filter(|(_, a)| **a == c)
                .map(|(d, _)| *d)
                .collect();
            if !members.is_empty() {
                *centre = majority(&members);
            }
        }
    }
    centres
}

/// A sparse, L1-normalized TF-IDF word histogram, sorted by word.
pub type BowVector = Vec<(u32, f64)>;

impl Vocabulary {
    /// Learn a vocabulary from the descriptors of each keyframe (`documents[k]`), and the
    /// inverse document frequency of each word over those keyframes.
    pub fn train(documents: &[Vec<Descriptor>]) -> Self {
        let all: Vec<&Descriptor> = documents.iter().flatten().collect();
        let roots = kmajority(&all, VOCABULARY_BRANCHING);
        let mut groups: Vec<Vec<&Descriptor>> = vec![Vec::new(); roots.len()];
        for d in &all {
            groups[nearest(d, &roots)].push(d);
        }
        let nodes: Vec<VocabularyNode> = roots
            .iter()
            .zip(&groups)
            .map(|(c, g)| {
                let mut words = kmajority(g, VOCABULARY_BRANCHING);
                if words.is_empty() {
                    words.push(*c);
                }
                VocabularyNode { centre: *c, words }
            })
            .collect();
        let mut vocab = Self {
            nodes,
            idf: Vec::new(),
        };
        let n_words = vocab.num_words();
        let mut df = vec![0u32; n_words];
        for doc in documents {
            let mut seen: Vec<u32> = doc.iter().map(|d| vocab.word(d)).collect();
            seen.sort_unstable();
            seen.dedup();
            for w in seen {
                df[w as usize] += 1;
            }
        }
        let n_docs = documents.len().max(1) as f64;
        vocab.idf = df
            .iter()
            .map(|&c| (n_docs / f64::from(c.max(1))).ln())
            .collect();
        vocab
    }

    /// Number of words.
    pub fn num_words(&self) -> usize {
        self.nodes.iter().map(|n| n.words.len()).sum()
    }

    /// Word id of a descriptor.
    pub fn word(&self, d: &Descriptor) -> u32 {
        let centres: Vec<Descriptor> = self.nodes.iter().map(|n| n.centre).collect();
        let r = nearest(d, &centres);
        let offset: usize = self.nodes[..r].iter().map(|n| n.words.len()).sum();
        (offset + nearest(d, &self.nodes[r].words)) as u32
    }

    /// Check sizes (for file validation): a message on failure.
    pub fn check(&self) -> Result<(), String> {
        if self.nodes.is_empty() || self.nodes.iter().any(|n| n.words.is_empty()) {
            return Err("expected non-empty nodes with at least one word each".into());
        }
        if self.idf.len() != self.num_words() {
            return Err(format!(
                "expected {} idf values (one per word), found {}",
                self.num_words(),
                self.idf.len()
            ));
        }
        if self.idf.iter().any(|v| !v.is_finite() || *v < 0.0) {
            return Err("expected finite, non-negative idf values".into());
        }
        Ok(())
    }

    /// The TF-IDF histogram of a set of descriptors.
    pub fn bow(&self, descriptors: &[Descriptor]) -> BowVector {
        let mut words: Vec<u32> = descriptors.iter().map(|d| self.word(d)).collect();
        words.sort_unstable();
        let mut v: BowVector = Vec::new();
        for w in words {
            let weight = self.idf.get(w as usize).copied().unwrap_or(0.0);
            match v.last_mut() {
                Some((last, acc)) if *last == w => *acc += weight,
                _ => v.push((w, weight)),
            }
        }
        let total: f64 = v.iter().map(|(_, x)| x.abs()).sum();
        if total > 0.0 {
            for (_, x) in &mut v {
                *x /= total;
            }
        }
        v.retain(|(_, x)| *x > 0.0);
        v
    }
}

/// L1 similarity of two normalized histograms in `[0, 1]`.
pub fn bow_score(a: &BowVector, b: &BowVector) -> f64 {
    // ‖a − b‖₁ = 2 − Σ_common (|a|+|b|−|a−b|) for L1-normalized non-negative vectors.
    let (mut i, mut j) = (0, 0);
    let mut s = 0.0;
    while i < a.len() && j < b.len() {
        match a[i].0.cmp(&b[j].0) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => {
                let (x, y) = (a[i].1, b[j].1);
                s += x + y - (x - y).abs();
                i += 1;
                j += 1;
            }
        }
    }
    0.5 * s
}

/// Keyframe database: each keyframe's histogram and an inverted index word → keyframes.
#[derive(Debug, Clone, Default)]
pub struct KeyframeDatabase {
    vectors: Vec<BowVector>,
    inverted: Vec<Vec<u32>>,
}

impl KeyframeDatabase {
    /// Index keyframes (their descriptors, in keyframe order).
    pub fn build(vocabulary: &Vocabulary, keyframes: &[Vec<Descriptor>]) -> Self {
        let vectors: Vec<BowVector> = keyframes.iter().map(|d| vocabulary.bow(d)).collect();
        let mut inverted = vec![Vec::new(); vocabulary.num_words()];
        for (k, v) in vectors.iter().enumerate() {
            for (w, _) in v {
                if let Some(list) = inverted.get_mut(*w as usize) {
                    list.push(k as u32);
                }
            }
        }
        Self { vectors, inverted }
    }

    /// The `max_results` keyframes most similar to `query` (score, keyframe), best first, ties
    /// by keyframe index.
    pub fn query(&self, query: &BowVector, max_results: usize) -> Vec<(f64, usize)> {
        let mut shares = vec![false; self.vectors.len()];
        for (w, _) in query {
            for &k in self.inverted.get(*w as usize).map_or(&[][..], |v| v) {
                shares[k as usize] = true;
            }
        }
        let mut scored: Vec<(f64, usize)> = shares
            .iter()
            .enumerate()
            .filter(|(_, s)| **s)
            .map(|(k, _)| (bow_score(query, &self.vectors[k]), k))
            .collect();
        scored.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        scored.truncate(max_results);
        scored
    }
}
