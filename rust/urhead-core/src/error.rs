//! Typed errors shared by every kernel. Each variant names the offending argument so the
//! Python binding can raise a specific exception with a message a user can act on.

/// What can be wrong with a kernel's inputs. Checked before any work is done.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Error {
    /// A tensor has the wrong number of elements or dimensions.
    #[error("{arg} must be {expected}, got {got}")]
    Shape {
        arg: &'static str,
        expected: String,
        got: String,
    },
    /// A tensor holds NaN or infinity where a finite value is required.
    #[error("{arg} must be finite, found {value} at flat index {index}")]
    NonFinite {
        arg: &'static str,
        index: usize,
        value: f64,
    },
    /// An index tensor points outside the range it indexes.
    #[error("{arg} holds {value} at flat index {index}, outside [{low}, {high})")]
    IndexOutOfRange {
        arg: &'static str,
        index: usize,
        value: i64,
        low: i64,
        high: i64,
    },
    /// A scalar or structural argument is invalid for another reason.
    #[error("{arg} is invalid: {reason}")]
    Invalid { arg: &'static str, reason: String },
    /// A size computation would overflow or exceed a configured limit.
    #[error("{what} needs {requested} elements, more than the limit of {limit}")]
    TooLarge {
        what: &'static str,
        requested: u128,
        limit: u128,
    },
    /// A buffer sized by the inputs cannot be allocated (the allocator refused it, or its
    /// byte count overflows).
    #[error("cannot allocate {what}: {elements} elements, {bytes} bytes")]
    OutOfMemory {
        what: &'static str,
        elements: usize,
        bytes: u128,
    },
}

pub type Result<T> = std::result::Result<T, Error>;

/// `Err(Shape)` unless `data.len() == expected_len`; `expected` describes the shape, e.g.
/// `"(V, 3) with V = 5023"`.
pub fn check_len<T>(arg: &'static str, data: &[T], expected_len: usize, expected: &str) -> Result<()> {
    if data.len() == expected_len {
        Ok(())
    } else {
        Err(Error::Shape {
            arg,
            expected: expected.to_string(),
            got: format!("{} elements", data.len()),
        })
    }
}

/// `Err(NonFinite)` naming the first NaN or infinity in `data`.
pub fn check_finite<T: crate::Real>(arg: &'static str, data: &[T]) -> Result<()> {
    match data.iter().position(|x| !x.is_finite()) {
        None => Ok(()),
        Some(index) => Err(Error::NonFinite {
            arg,
            index,
            value: data[index].to_f64().unwrap_or(f64::NAN),
        }),
    }
}

/// `Err(IndexOutOfRange)` naming the first index outside `[low, high)`.
pub fn check_indices<I: Copy + Into<i64>>(arg: &'static str, data: &[I], low: i64, high: i64) -> Result<()> {
    match data.iter().position(|&i| i.into() < low || i.into() >= high) {
        None => Ok(()),
        Some(index) => Err(Error::IndexOutOfRange {
            arg,
            index,
            value: data[index].into(),
            low,
            high,
        }),
    }
}

/// Product of `dims` with overflow and limit checks, for allocation sizes.
pub fn checked_size(what: &'static str, dims: &[usize], limit: usize) -> Result<usize> {
    let requested: u128 = dims.iter().map(|&d| d as u128).product();
    if requested > limit as u128 {
        Err(Error::TooLarge {
            what,
            requested,
            limit: limit as u128,
        })
    } else {
        Ok(requested as usize)
    }
}
