//! [`ServoArray`]: one value per servo of the chain in a fixed-size array (at most [`MAX_SERVOS`]),
//! so that the control cycle's buffers (goals, readings, per-servo results) live inline, are
//! allocated once with their owner and are overwritten every cycle without touching the heap.

/// The most servos one chain (one [`crate::servo_bus::ServoBus`]) carries: the 12 leg servos.
pub const MAX_SERVOS: usize = 12;

/// Error of [`ServoArray::try_from_slice`]: more values than [`MAX_SERVOS`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("{0} servos on one chain, at most {MAX_SERVOS} are supported")]
pub struct TooManyServos(pub usize);

/// Up to [`MAX_SERVOS`] values, one per servo in chain order; derefs to the slice of its `len`
/// values.
#[derive(Clone, Copy)]
pub struct ServoArray<T> {
    values: [T; MAX_SERVOS],
    len: usize,
}

impl<T: Default> ServoArray<T> {
    /// `len` default values (`len` is capped at [`MAX_SERVOS`]).
    pub fn filled(len: usize) -> Self {
        Self { values: std::array::from_fn(|_| T::default()), len: len.min(MAX_SERVOS) }
    }
}

impl<T: Default + Clone> ServoArray<T> {
    /// A copy of `values`; refused when there are more than [`MAX_SERVOS`].
    pub fn try_from_slice(values: &[T]) -> Result<Self, TooManyServos> {
        if values.len() > MAX_SERVOS {
            return Err(TooManyServos(values.len()));
        }
        let mut array = Self::filled(values.len());
        array.clone_from_slice(values);
        Ok(array)
    }

    /// The values of `iter` (at most [`MAX_SERVOS`]; any beyond are ignored).
    pub fn collect_from(iter: impl IntoIterator<Item = T>) -> Self {
        let mut array = Self::filled(0);
        for value in iter.into_iter().take(MAX_SERVOS) {
            array.push(value);
        }
        array
    }
}

impl<T> ServoArray<T> {
    /// Append a value; returns `false` (and drops nothing) when the array is full.
    pub fn push(&mut self, value: T) -> bool {
        match self.values.get_mut(self.len) {
            Some(slot) => {
                *slot = value;
                self.len += 1;
                true
            }
            None => false,
        }
    }

    /// Forget the values (they are overwritten by later pushes).
    pub fn clear(&mut self) {
        self.len = 0;
    }
}

impl<T: Default> Default for ServoArray<T> {
    fn default() -> Self {
        Self::filled(0)
    }
}

impl<T> std::ops::Deref for ServoArray<T> {
    type Target = [T];
    fn deref(&self) -> &[T] {
        self.values.get(..self.len).unwrap_or(&[])
    }
}

impl<T> std::ops::DerefMut for ServoArray<T> {
    fn deref_mut(&mut self) -> &mut [T] {
        self.values.get_mut(..self.len).unwrap_or(&mut [])
    }
}

impl<'a, T> IntoIterator for &'a ServoArray<T> {
    type Item = &'a T;
    type IntoIter = std::slice::Iter<'a, T>;
    fn into_iter(self) -> Self::IntoIter {
        self.iter()
    }
}

impl<T: PartialEq> PartialEq for ServoArray<T> {
    fn eq(&self, other: &Self) -> bool {
        **self == **other
    }
}

impl<T: std::fmt::Debug> std::fmt::Debug for ServoArray<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_list().entries(self.iter()).finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn holds_up_to_twelve_values_inline() {
        let mut array = ServoArray::<u8>::filled(2);
        assert_eq!(&*array, &[0, 0]);
        array[1] = 7;
        assert!(array.push(3));
        assert_eq!(&*array, &[0, 7, 3]);
        let full = ServoArray::collect_from(0..20u8);
        assert_eq!(full.len(), MAX_SERVOS);
        let mut more = full;
        assert!(!more.push(99), "a full array refuses");
        assert_eq!(more, full);
        assert_eq!(ServoArray::try_from_slice(&[1.0, 2.0]).map(|a| a.to_vec()), Ok(vec![1.0, 2.0]));
        assert_eq!(ServoArray::<u8>::try_from_slice(&[0; 13]), Err(TooManyServos(13)));
        assert_eq!(format!("{:?}", ServoArray::collect_from([Some(1), None])), "[Some(1), None]");
        array.clear();
        assert!(array.is_empty());
    }
}
