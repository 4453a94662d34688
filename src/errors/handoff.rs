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
//!
//! [`AtlasLayers`] extends the same rules to the heightfield atlas of a streamed terrain
//! (SPEC section 8): a tile is drawable once the generation that uploaded it finished, and
//! its layer is reused only after every frame that drew from it completed. The atlas
//! and its thread ([`crate::errors::atlas`]) keep these rules under one lock.

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

/// The heightfield atlas's layers (SPEC section 8, "Residency"), the same hand-off for
/// tiles: the errors activity uploads a tile into a layer as part of generation `g`; the
/// draw thread draws from it only once `g` is finished (its errors were computed in the
/// same generation); a layer is reused only after every frame that drew from it has
/// completed on the GPU (the draw queue's timeline has passed the last such frame), and
/// every errors generation that read it has finished (with two generations in flight,
/// an upload may be recorded while the generation before it still shades). Both sides
/// read the other's counter and never wait on it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct AtlasLayers<T> {
    layers: Vec<Layer<T>>,
    /// The newest generation finished.
    finished: u64,
}

/// One layer's state.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Layer<T> {
    Free,
    /// Being written by generation `generation` (not drawable until it finishes).
    Uploading {
        tile: T,
        generation: u64,
    },
    /// Holds `tile`; `last_frame` is the newest frame that drew from it (0: none),
    /// `errors_read` the newest errors generation that reads it (0: none).
    Resident {
        tile: T,
        generation: u64,
        last_frame: u64,
        errors_read: u64,
    },
}

impl<T: Copy + PartialEq + std::fmt::Debug> AtlasLayers<T> {
    pub fn new(layers: usize) -> Self {
        AtlasLayers { layers: vec![Layer::Free; layers], finished: 0 }
    }

    pub fn layer(&self, i: usize) -> &Layer<T> {
        &self.layers[i]
    }

    /// The layer `tile` is in, whatever its state.
    pub fn find(&self, tile: T) -> Option<usize> {
        self.layers.iter().position(|l| match l {
            Layer::Free => false,
            Layer::Uploading { tile: t, .. } | Layer::Resident { tile: t, .. } => *t == tile,
        })
    }

    /// A layer for `tile` in generation `generation`: a free one, else the resident
    /// layer drawn longest ago among those every frame that drew from has completed
    /// (`completed_frame`, the draw timeline's value), that no unfinished errors
    /// generation reads, and that `keep` does not protect.
    /// `None` when there is none: the tile waits.
    pub fn claim(&mut self, tile: T, generation: u64, completed_frame: u64, keep: impl Fn(T) -> bool) -> Option<usize> {
        assert!(self.find(tile).is_none(), "{tile:?} is in the atlas already");
        let free = self.layers.iter().position(|l| *l == Layer::Free);
        let reusable = || {
            self.layers
                .iter()
                .enumerate()
                .filter_map(|(i, l)| match l {
                    Layer::Resident { tile, last_frame, errors_read, .. }
                        if *last_frame <= completed_frame && *errors_read <= self.finished && !keep(*tile) =>
                    {
                        Some((*last_frame, i))
                    }
                    _ => None,
                })
                .min()
                .map(|(_, i)| i)
        };
        let i = free.or_else(reusable)?;
        self.layers[i] = Layer::Uploading { tile, generation };
        Some(i)
    }

    /// Generation `g` finished: what it uploaded is drawable, and what it read may be
    /// reused.
    pub fn finish(&mut self, g: u64) {
        self.finished = self.finished.max(g);
        for l in &mut self.layers {
            if let Layer::Uploading { tile, generation } = *l {
                if generation <= g {
                    *l = Layer::Resident { tile, generation, last_frame: 0, errors_read: 0 };
                }
            }
        }
    }

    /// Errors generation `g` reads layer `i` (resident): kept until `g` finishes.
    pub fn read_for_errors(&mut self, i: usize, g: u64) {
        match &mut self.layers[i] {
            Layer::Resident { errors_read, .. } => *errors_read = (*errors_read).max(g),
            l => panic!("generation {g} reads layer {i}, which is not resident: {l:?}"),
        }
    }

    /// The layer the draw thread may draw `tile` from in frame `frame`, recording the
    /// draw (the layer is then kept until that frame completes); `None` if it is not
    /// resident yet.
    pub fn draw(&mut self, tile: T, frame: u64) -> Option<usize> {
        let i = self.find(tile)?;
        match &mut self.layers[i] {
            Layer::Resident { last_frame, .. } => {
                assert!(frame >= *last_frame, "frames are numbered in order");
                *last_frame = frame;
                Some(i)
            }
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small deterministic generator of choices below `n` (xorshift64).
    fn xorshift(seed: u64) -> impl FnMut(u64) -> u64 {
        let mut rng = seed;
        move |n| {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            rng % n
        }
    }

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
        let mut next = xorshift(seed);
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

    /// What each atlas layer's memory holds, and the GPU work on it.
    #[derive(Clone, Copy, Debug, PartialEq)]
    enum LayerMemory {
        Empty,
        Writing(u32),
        Holds(u32),
    }

    /// Random interleavings of the errors thread (claim a layer and upload a tile in a
    /// generation, the GPU finishing uploads and generations in order) and the draw
    /// thread (frames that draw from resident tiles, completing in order, the timeline
    /// read late): no upload starts on a layer a frame still in flight reads, no frame
    /// reads a layer being written, and every read finds the tile it asked for.
    fn explore_atlas(seed: u64, steps: usize) -> (u64, u64) {
        let mut next = xorshift(seed);
        const LAYERS: usize = 4;
        const TILES: u32 = 9;
        let mut atlas = AtlasLayers::<u32>::new(LAYERS);
        let mut memory = [LayerMemory::Empty; LAYERS];
        let (mut generation, mut finished) = (1u64, 0u64);
        // Uploads submitted (layer, tile, generation) whose GPU write is not done.
        let mut writes: Vec<(usize, u32, u64)> = Vec::new();
        // Frames submitted and not completed: (frame, reads of (layer, tile)).
        let mut frames: std::collections::VecDeque<(u64, Vec<(usize, u32)>)> = Default::default();
        let (mut frame, mut completed, mut seen_completed) = (0u64, 0u64, 0u64);
        // Errors passes of the open generation, in flight: (layer, tile, generation).
        let mut error_reads: Vec<(usize, u32, u64)> = Vec::new();
        let mut reuses = 0;
        for _ in 0..steps {
            match next(8) {
                // The errors thread claims a layer for a tile not in the atlas.
                0 => {
                    let tile = next(u64::from(TILES)) as u32;
                    if atlas.find(tile).is_some() {
                        continue;
                    }
                    let was_free = atlas.layers.contains(&Layer::Free);
                    if let Some(i) = atlas.claim(tile, generation, seen_completed, |_| false) {
                        for (f, reads) in &frames {
                            assert!(
                                reads.iter().all(|(l, _)| *l != i),
                                "frame {f}, in flight, reads layer {i}: the upload of {tile} overwrites it"
                            );
                        }
                        for (l, t, g) in &error_reads {
                            assert!(
                                *l != i,
                                "errors generation {g}, in flight, reads {t} in layer {i}: {tile} overwrites it"
                            );
                        }
                        reuses += u64::from(!was_free);
                        memory[i] = LayerMemory::Writing(tile);
                        writes.push((i, tile, generation));
                    }
                }
                // The GPU finishes the oldest upload.
                1 if !writes.is_empty() => {
                    let (i, tile, _) = writes.remove(0);
                    memory[i] = LayerMemory::Holds(tile);
                }
                // The generation is published once all its uploads are done, and so are its
                // errors passes: what they read was there all along.
                2 if writes.iter().all(|w| w.2 > generation) => {
                    for (l, t, g) in error_reads.drain(..) {
                        assert_eq!(
                            memory[l],
                            LayerMemory::Holds(t),
                            "errors generation {g}: layer {l} changed under it"
                        );
                    }
                    finished = generation;
                    atlas.finish(finished);
                    generation += 1;
                }
                // The errors thread shades a few resident tiles in the open generation
                // (with uploads of the same or the next generation still to come).
                6 => {
                    for _ in 0..2 {
                        let tile = next(u64::from(TILES)) as u32;
                        let Some(i) = atlas.find(tile) else { continue };
                        if matches!(atlas.layer(i), Layer::Resident { .. }) {
                            assert_eq!(
                                memory[i],
                                LayerMemory::Holds(tile),
                                "errors generation {generation} reads layer {i}"
                            );
                            atlas.read_for_errors(i, generation);
                            error_reads.push((i, tile, generation));
                        }
                    }
                }
                // The draw thread submits a frame drawing a few resident tiles.
                3 | 4 => {
                    frame += 1;
                    let mut reads = Vec::new();
                    for _ in 0..3 {
                        let tile = next(u64::from(TILES)) as u32;
                        if let Some(i) = atlas.draw(tile, frame) {
                            assert_eq!(memory[i], LayerMemory::Holds(tile), "frame {frame} reads layer {i}");
                            reads.push((i, tile));
                        }
                    }
                    frames.push_back((frame, reads));
                }
                // The GPU completes the oldest frame: its reads found their tiles.
                5 => {
                    if let Some((f, reads)) = frames.pop_front() {
                        for (i, tile) in reads {
                            assert_eq!(memory[i], LayerMemory::Holds(tile), "frame {f}: layer {i} changed under it");
                        }
                        completed = f;
                    }
                }
                // The errors thread reads the draw timeline (late, as it may be).
                _ => seen_completed = completed,
            }
        }
        (reuses, finished)
    }

    #[test]
    fn no_interleaving_overwrites_an_atlas_layer_a_frame_reads() {
        let mut reuses = 0;
        for seed in 1..=300u64 {
            let (r, finished) = explore_atlas(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1, 3000);
            assert!(finished > 50, "seed {seed}: only {finished} generations");
            reuses += r;
        }
        assert!(reuses > 300, "layers were reused only {reuses} times: the model does not exercise reuse");
    }

    /// The rules, one by one: not drawable before its generation finishes; not reused
    /// while a frame that drew from it is in flight; reused drawn-longest-ago first;
    /// kept tiles are not taken.
    #[test]
    fn an_atlas_layer_waits_for_its_generation_and_its_last_frame() {
        let mut a = AtlasLayers::<u32>::new(2);
        assert_eq!(a.claim(10, 1, 0, |_| false), Some(0));
        assert_eq!(a.claim(11, 1, 0, |_| false), Some(1));
        assert_eq!(a.draw(10, 1), None, "generation 1 is not finished");
        a.finish(1);
        assert_eq!((a.draw(10, 1), a.draw(11, 2)), (Some(0), Some(1)));
        assert_eq!(a.claim(12, 2, 0, |_| false), None, "frames 1 and 2 are in flight");
        assert_eq!(a.claim(12, 2, 1, |_| false), Some(0), "frame 1 completed: tile 10's layer");
        assert_eq!(a.claim(13, 2, 2, |t| t == 11), None, "11 is kept");
        assert_eq!(a.claim(13, 2, 2, |_| false), Some(1));
        assert_eq!(a.draw(12, 3), None, "generation 2 is not finished");
        a.finish(2);
        assert_eq!(a.draw(12, 3), Some(0));
        // An errors generation in flight (3) reads tile 12's layer: not reused before 3
        // finishes, however long ago a frame drew it.
        a.read_for_errors(0, 3);
        a.finish(3);
        a.read_for_errors(0, 4);
        assert_eq!(a.claim(14, 5, 9, |t| t == 13), None, "generation 4 reads tile 12");
        a.finish(4);
        assert_eq!(a.claim(14, 5, 9, |t| t == 13), Some(0));
    }
}
