//! The hand-off between the errors thread (the writer) and the draw thread (the reader)
//! over two slots of GPU targets and host-visible readback buffers (SPEC section 4), as
//! plain state, so that its rules are tested without a GPU.
//!
//! Generation `g` is written into slot `g % 2`. The reader copies the newest finished
//! generation out of its slot and releases it; from then on it works from its copy. So
//! the writer may reuse a slot as soon as the generation it held is either released or
//! superseded by a finished one (the reader only ever takes the newest), and is not
//! being copied right now. That lets two generations be in flight, `g - 1` and `g`, both
//! slots written at once, while the reader draws with its copy of `g - 2`.

/// Slots (error targets and readback buffers) used in turn.
pub const SLOTS: u64 = 2;
/// Generations written at once, at most: one per slot.
pub const MAX_IN_FLIGHT: u64 = SLOTS;

/// The protocol's state, kept under one lock shared by the two threads.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Handoff {
    /// Newest generation started (its slot is being written until it finishes).
    started: u64,
    /// Newest generation finished and published: readable in its slot.
    finished: u64,
    /// Generation the reader is copying right now.
    reading: Option<u64>,
    /// Newest generation the reader has finished copying.
    released: u64,
}

/// What the reader should do, from [`Handoff::begin_read`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Read {
    /// Nothing finished yet.
    Nothing,
    /// The newest finished generation was copied already: use that copy (its slot may
    /// be being written again).
    Copied(u64),
    /// Copy `generation` out of `slot`, then call [`Handoff::end_read`].
    Copy { generation: u64, slot: usize },
}

impl Handoff {
    /// The slot generation `g` is written into.
    pub fn slot(g: u64) -> usize {
        (g % SLOTS) as usize
    }

    pub fn started(&self) -> u64 {
        self.started
    }

    pub fn finished(&self) -> u64 {
        self.finished
    }

    /// Generations started and not yet finished.
    pub fn in_flight(&self) -> u64 {
        self.started - self.finished
    }

    /// Whether the writer may start the next generation now.
    pub fn can_start(&self) -> bool {
        let g = self.started + 1;
        if g <= SLOTS {
            return true; // its slot was never used
        }
        let previous = g - SLOTS; // the generation its slot holds
                                  // The reader will never copy `previous` again: it has its copy, or a newer
                                  // generation is finished (it only ever takes the newest). Either way `previous`
                                  // is finished, so at most `g - 1` and `g` are in flight.
        let superseded = self.released >= previous || self.finished > previous;
        superseded && self.reading != Some(previous)
    }

    /// Starts the next generation; returns its number. Call only when [`Self::can_start`].
    pub fn start(&mut self) -> u64 {
        assert!(self.can_start(), "generation {} started against the protocol: {self:?}", self.started + 1);
        self.started += 1;
        self.started
    }

    /// Generation `g` is written (the GPU signalled it) and published, in order.
    pub fn finish(&mut self, g: u64) {
        assert!(g == self.finished + 1 && g <= self.started, "generation {g} finished out of order: {self:?}");
        self.finished = g;
    }

    /// The reader starts taking the newest finished generation.
    pub fn begin_read(&mut self) -> Read {
        let g = self.finished;
        if g == 0 {
            Read::Nothing
        } else if g <= self.released {
            Read::Copied(g)
        } else {
            self.reading = Some(g);
            Read::Copy { generation: g, slot: Self::slot(g) }
        }
    }

    /// The reader has copied `g` (or given up on it): its slot may be reused.
    pub fn end_read(&mut self, g: u64, copied: bool) {
        assert_eq!(self.reading, Some(g), "end of a read that was not begun");
        self.reading = None;
        if copied {
            self.released = self.released.max(g);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A model of the two slots' memory: what each holds, and whether the GPU is
    /// writing it right now.
    #[derive(Clone, Copy, Debug, PartialEq)]
    enum Memory {
        Empty,
        Writing(u64),
        Holds(u64),
    }

    /// Random interleavings of the writer (start, GPU done, publish) and a reader
    /// (begin, copy, end), checked against the memory model: a copy never overlaps a
    /// write of its slot, and always finds the generation it was told to take.
    fn explore(seed: u64, steps: usize) -> (u64, u64) {
        let mut rng = seed;
        let mut next = move |n: u64| {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            rng % n
        };
        let mut h = Handoff::default();
        let mut memory = [Memory::Empty; SLOTS as usize];
        // Generations the GPU has done but the writer has not published yet.
        let mut gpu_done = 0u64;
        let mut copying: Option<(u64, usize)> = None;
        let mut reader_has = 0u64;
        let mut most_in_flight = 0;
        for _ in 0..steps {
            match next(6) {
                0 if h.can_start() => {
                    let g = h.start();
                    let slot = Handoff::slot(g);
                    if let Some((c, s)) = copying {
                        assert!(s != slot, "generation {g} starts writing slot {s} while {c} is copied from it");
                    }
                    if let Memory::Writing(w) = memory[slot] {
                        panic!("generation {g} starts writing slot {slot} while the GPU still writes {w}");
                    }
                    memory[slot] = Memory::Writing(g);
                    most_in_flight = most_in_flight.max(h.in_flight());
                    assert!(h.in_flight() <= MAX_IN_FLIGHT);
                }
                1 if gpu_done < h.started() => {
                    gpu_done += 1; // the GPU finishes in submission order
                    memory[Handoff::slot(gpu_done)] = Memory::Holds(gpu_done);
                }
                2 if h.finished() < gpu_done => h.finish(h.finished() + 1),
                3 if copying.is_none() => match h.begin_read() {
                    Read::Nothing => assert_eq!(reader_has, 0),
                    Read::Copied(g) => assert_eq!(g, reader_has, "told to use a copy it does not have"),
                    Read::Copy { generation, slot } => {
                        assert!(generation > reader_has, "went back from {reader_has} to {generation}");
                        assert_eq!(memory[slot], Memory::Holds(generation), "copy of {generation} from slot {slot}");
                        copying = Some((generation, slot));
                    }
                },
                4 => {
                    if let Some((g, slot)) = copying.take() {
                        assert_eq!(memory[slot], Memory::Holds(g), "generation {g} overwritten while copied");
                        h.end_read(g, true);
                        reader_has = g;
                    }
                }
                // A read that fails (a mapping error): the reader keeps its older copy.
                5 if next(4) == 0 => {
                    if let Some((g, _)) = copying.take() {
                        h.end_read(g, false);
                    }
                }
                _ => {}
            }
        }
        (most_in_flight, h.finished())
    }

    #[test]
    fn no_interleaving_tears_a_read() {
        let mut two_in_flight = 0;
        for seed in 1..=300u64 {
            let (most, finished) = explore(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1, 2000);
            assert!(finished > 50, "seed {seed}: only {finished} generations in 2000 steps");
            two_in_flight += (most == 2) as u32;
        }
        assert!(two_in_flight > 250, "two generations in flight in only {two_in_flight} of 300 runs");
    }

    #[test]
    fn two_in_flight_while_the_reader_holds_a_copy() {
        let mut h = Handoff::default();
        assert_eq!(h.begin_read(), Read::Nothing);
        assert_eq!((h.start(), h.start()), (1, 2), "both slots are free at first");
        assert!(!h.can_start(), "two in flight");
        h.finish(1);
        // Generation 1 is finished and not yet copied: slot 1 must wait for the reader.
        assert!(!h.can_start());
        assert_eq!(h.begin_read(), Read::Copy { generation: 1, slot: 1 });
        assert!(!h.can_start(), "being copied");
        h.end_read(1, true);
        assert_eq!(h.start(), 3, "released: 2 and 3 in flight, the reader draws with its copy of 1");
        assert_eq!(h.in_flight(), 2);
        assert_eq!(h.begin_read(), Read::Copied(1));
        h.finish(2);
        // Slot 0 holds 2 now, not yet copied, and 4 would overwrite it: wait for 3 to
        // supersede it or for the reader to copy it.
        assert!(!h.can_start());
        h.finish(3);
        assert!(h.can_start(), "3 supersedes 2: the reader will never take 2");
        assert_eq!(h.begin_read(), Read::Copy { generation: 3, slot: 1 });
        assert_eq!(h.start(), 4, "slot 0 (generation 2) is free while 3 is copied from slot 1");
        assert!(!h.can_start(), "5 would write slot 1, being copied");
        h.end_read(3, true);
        assert!(h.can_start());
    }

    #[test]
    fn a_reader_that_gives_up_keeps_the_slot_claimed() {
        let mut h = Handoff::default();
        h.start();
        h.start();
        h.finish(1);
        assert_eq!(h.begin_read(), Read::Copy { generation: 1, slot: 1 });
        h.end_read(1, false);
        assert!(!h.can_start(), "1 is not copied: its slot stays until 2 is finished");
        assert_eq!(h.begin_read(), Read::Copy { generation: 1, slot: 1 }, "asked again, it is copied again");
        h.end_read(1, true);
        assert!(h.can_start());
    }

    #[test]
    #[should_panic(expected = "out of order")]
    fn finishing_out_of_order_is_refused() {
        let mut h = Handoff::default();
        h.start();
        h.start();
        h.finish(2);
    }
}
