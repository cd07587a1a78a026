//! Deterministic synthetic inputs shared by tests and benches (no files, no Python).

use crate::lbs::LbsModel;
use crate::Real;

/// SplitMix64: a small, well-mixed, reproducible generator.
#[derive(Debug, Clone)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [lo, hi).
    pub fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    pub fn vec<T: Real>(&mut self, n: usize, lo: f64, hi: f64) -> Vec<T> {
        (0..n).map(|_| T::c(self.uniform(lo, hi))).collect()
    }
}

/// Owned tables of a random skinned model with a FLAME-like chain (parents
/// `[-1, 0, 1, 1, 1, …]`), sparse-ish weights summing to 1 and a normalised regressor.
#[derive(Debug, Clone)]
pub struct SyntheticLbs<T> {
    pub v_template: Vec<T>,
    pub shapedirs: Vec<T>,
    pub posedirs: Vec<T>,
    pub j_regressor: Vec<T>,
    pub parents: Vec<i32>,
    pub lbs_weights: Vec<T>,
    pub num_verts: usize,
    pub num_betas: usize,
    pub num_joints: usize,
}

impl<T: Real> SyntheticLbs<T> {
    pub fn new(num_verts: usize, num_betas: usize, num_joints: usize, seed: u64) -> Self {
        let (v, nb, nj) = (num_verts, num_betas, num_joints);
        let mut rng = Rng::new(seed);
        let v_template = rng.vec(v * 3, -0.1, 0.1);
        let shapedirs = rng.vec(v * 3 * nb, -1e-3, 1e-3);
        let posedirs = rng.vec(9 * (nj - 1) * v * 3, -1e-3, 1e-3);
        let mut j_regressor = vec![T::zero(); nj * v];
        for j in 0..nj {
            let picks: Vec<usize> = (0..8).map(|_| (rng.next_u64() % v as u64) as usize).collect();
            for &p in &picks {
                j_regressor[j * v + p] += T::c(1.0 / 8.0);
            }
        }
        let mut lbs_weights = vec![T::zero(); v * nj];
        for i in 0..v {
            let a = (rng.next_u64() % nj as u64) as usize;
            let b = (rng.next_u64() % nj as u64) as usize;
            let w = rng.uniform(0.2, 0.8);
            lbs_weights[i * nj + a] += T::c(w);
            lbs_weights[i * nj + b] += T::c(1.0 - w);
        }
        let parents = (0..nj as i32)
            .map(|j| {
                if j == 0 {
                    -1
                } else if j == 1 {
                    0
                } else {
                    1
                }
            })
            .collect();
        Self {
            v_template,
            shapedirs,
            posedirs,
            j_regressor,
            parents,
            lbs_weights,
            num_verts,
            num_betas,
            num_joints,
        }
    }

    pub fn model(&self) -> LbsModel<'_, T> {
        LbsModel::new(
            &self.v_template,
            &self.shapedirs,
            &self.posedirs,
            &self.j_regressor,
            &self.parents,
            &self.lbs_weights,
            self.num_verts,
            self.num_betas,
            self.num_joints,
        )
        .expect("synthetic model is valid")
    }
}

/// Environment variable naming the file [`record_stability`] appends to.
pub const STABILITY_LOG_ENV: &str = "URHEAD_STABILITY_LOG";

/// A NUMERICS.md check for the stability report: asserts `worst <= tolerance` (a NaN
/// `worst` fails) and, when `URHEAD_STABILITY_LOG` names a file, first appends one JSON line
/// `{"case", "check", "test", "worst", "tolerance"}` to it, so a failed bound is recorded
/// too. `pytest --stability-rust-log <file>` merges the lines into docs/stability.md.
pub fn record_stability(case: u32, check: &str, test: &str, worst: f64, tolerance: f64) {
    if let Some(path) = std::env::var_os(STABILITY_LOG_ENV) {
        use std::io::Write;
        // JSON has no NaN: a NaN worst is logged as +inf, which fails every bound too.
        let logged = if worst.is_nan() { f64::INFINITY } else { worst };
        let line = format!(
            "{{\"case\": {case}, \"check\": {}, \"test\": {}, \"worst\": {}, \"tolerance\": {}}}\n",
            json_string(check),
            json_string(test),
            json_number(logged),
            json_number(tolerance)
        );
        // One write per line on an O_APPEND file: lines from parallel tests do not interleave.
        if let Some(dir) = std::path::Path::new(&path).parent() {
            std::fs::create_dir_all(dir).ok();
        }
        let mut file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .expect("URHEAD_STABILITY_LOG must name a writable file");
        file.write_all(line.as_bytes())
            .expect("writing the stability log");
    }
    assert!(
        worst <= tolerance,
        "case {case}, {check}: worst {worst:e} > tolerance {tolerance:e}"
    );
}

fn json_string(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 2);
    out.push('"');
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            c if (c as u32) < 0x20 => out.push_str(&format!("\\u{:04x}", c as u32)),
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

/// Python's json reads `Infinity`; finite values print exactly (shortest round-trip).
fn json_number(x: f64) -> String {
    if x.is_infinite() {
        if x > 0.0 { "Infinity" } else { "-Infinity" }.to_string()
    } else {
        format!("{x:e}")
    }
}

/// Runs `f` on a fresh rayon pool of `threads` threads: the thread-count checks (results
/// must be the same bits for any count) run each pass under several pools.
pub fn on_threads<R: Send>(threads: usize, f: impl FnOnce() -> R + Send) -> R {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("a rayon pool for the test")
        .install(f)
}

/// A jittered latitude–longitude sphere of radius 1 centred at (0, 0, 3): (verts, faces).
pub fn sphere(n_lat: usize, n_lon: usize, jitter: f64, seed: u64) -> (Vec<f64>, Vec<i32>) {
    let mut rng = Rng::new(seed);
    let mut verts = Vec::new();
    for i in 0..=n_lat {
        let theta = std::f64::consts::PI * i as f64 / n_lat as f64;
        for j in 0..n_lon {
            let phi = 2.0 * std::f64::consts::PI * j as f64 / n_lon as f64;
            verts.push(theta.sin() * phi.cos() + rng.uniform(-jitter, jitter));
            verts.push(theta.cos() + rng.uniform(-jitter, jitter));
            verts.push(3.0 + theta.sin() * phi.sin() + rng.uniform(-jitter, jitter));
        }
    }
    let mut faces = Vec::new();
    for i in 0..n_lat {
        for j in 0..n_lon {
            let (a, b) = (i * n_lon + j, i * n_lon + (j + 1) % n_lon);
            let (c, d) = ((i + 1) * n_lon + j, (i + 1) * n_lon + (j + 1) % n_lon);
            faces.extend([a, c, b, b, c, d].map(|x| x as i32));
        }
    }
    (verts, faces)
}
