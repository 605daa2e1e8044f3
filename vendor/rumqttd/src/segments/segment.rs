use crate::{Cursor, Offset};

use super::Storage;
use std::io;

/// fbbus: entries per chunk of a segment (see `Segment::data`).
const CHUNK: usize = 1024;

pub(crate) struct Segment<T> {
    /// Holds the actual segment. fbbus: in chunks of `CHUNK` entries. Upstream kept one
    /// `Vec` per segment; a busy filter's segment grew to tens of thousands of entries by
    /// doubling, and each doubling copied the whole segment on the router thread (up to
    /// 15 ms at 10,000 msg/s, the steady-rate latency maximum). A chunk never moves once
    /// allocated; only the first one grows, so an idle topic still costs little.
    data: Vec<Vec<T>>,
    /// Entries in `data`.
    len: usize,
    total_size: u64,
    /// The absolute offset at which the `inner` starts at. All reads will return the absolute
    /// offset as the offset of the cursor.
    ///
    /// **NOTE**: this offset is re-generated on each run of the commit log.
    pub(crate) absolute_offset: u64,
}

pub(crate) enum SegmentPosition {
    /// When the returned absolute offset exists within the current segment
    Next(u64),
    /// When the the returned absolute offset does not exist within the current segment, but
    /// instead is 1 beyond the highest absolute offset in this segment, meant for use with next
    /// segment if any exists.
    Done(u64),
}

impl<T> Segment<T>
where
    T: Storage + Clone,
{
    // fbbus: segments start unallocated (upstream reserved 1,024 entries, ~300 KB, for
    // every filter, including the dynamic filter of every topic ever published).
    pub(crate) fn with_offset(absolute_offset: u64) -> Self {
        Self {
            data: Vec::new(),
            len: 0,
            absolute_offset,
            total_size: 0,
        }
    }
    pub(crate) fn new() -> Self {
        Self::with_offset(0)
    }

    #[inline]
    pub(crate) fn next_offset(&self) -> u64 {
        self.absolute_offset + self.len()
    }

    /// Push a new `T` in the segment.
    #[inline]
    pub(crate) fn push(&mut self, inner_type: T) {
        self.total_size += inner_type.size() as u64;
        // fbbus: a full chunk stays where it is; the next one is allocated at its full size.
        match self.data.last_mut() {
            Some(chunk) if chunk.len() < CHUNK => chunk.push(inner_type),
            Some(_) => {
                let mut chunk = Vec::with_capacity(CHUNK);
                chunk.push(inner_type);
                self.data.push(chunk);
            }
            None => self.data.push(vec![inner_type]),
        }
        self.len += 1;
    }

    #[inline]
    /// Takes in the abosolute index to start reading from. Internally handles the conversion from
    /// relative offset to absolute offset and vice-versa.
    pub(crate) fn readv(
        &self,
        cursor: Cursor,
        len: u64,
        out: &mut Vec<(T, Offset)>,
    ) -> io::Result<SegmentPosition> {
        // This substraction can never overflow as checking of offset happens at
        // `CommitLog::readv`.
        let idx = cursor.1 - self.absolute_offset;

        let mut ret: Option<u64>;

        if idx >= self.len() {
            ret = None;
        } else {
            // fbbus: saturating: `len` is the configured read size for QoS 0
            // (`max_outgoing_packet_count`, any u64), and `idx + len` overflowed near the top.
            let mut limit = idx.saturating_add(len);

            ret = Some(limit);

            if limit >= self.len() {
                ret = None;
                limit = self.len();
            }
            // fbbus: `limit` is an index here (upstream zipped `cursor.1..cursor.1 + limit`,
            // longer than the slice; `zip` stopped at the slice's end).
            let offsets = std::iter::repeat(cursor.0).zip(cursor.1..);
            let o = (idx as usize..limit as usize)
                .map(|i| self.data[i / CHUNK][i % CHUNK].clone())
                .zip(offsets);
            out.extend(o);
        }

        match ret {
            Some(relative_offset) => Ok(SegmentPosition::Next(
                self.absolute_offset + relative_offset,
            )),
            None => Ok(SegmentPosition::Done(self.next_offset())),
        }
    }

    /// fbbus: whether the segment holds memory (entries or reserved capacity).
    #[inline]
    pub(crate) fn is_allocated(&self) -> bool {
        !self.data.is_empty()
    }

    /// Get the number of `T` in the segment.
    #[inline]
    pub(crate) fn len(&self) -> u64 {
        self.len as u64
    }

    /// Get the total size in bytes of the segment.
    #[inline]
    pub(crate) fn size(&self) -> u64 {
        self.total_size
    }

    #[inline]
    pub fn last(&self) -> Option<T> {
        self.data.last().and_then(|chunk| chunk.last()).cloned()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bytes::Bytes;

    #[test]
    fn segment_works_for_bytes() {
        let mut mem_segment: Segment<Bytes> = Segment::new();
        let test_byte = Bytes::from_static(b"test1");
        mem_segment.push(test_byte.clone());
        assert_eq!(mem_segment.len(), 1);
        assert_eq!(mem_segment.last().unwrap(), test_byte);
    }

    #[test]
    fn readv_works_for_bytes() {
        let mut segment: Segment<Bytes> = Segment::new();
        segment.push(Bytes::from_static(b"test1"));
        segment.push(Bytes::from_static(b"test2"));
        segment.push(Bytes::from_static(b"test3"));
        segment.push(Bytes::from_static(b"test4"));
        segment.push(Bytes::from_static(b"test5"));
        segment.push(Bytes::from_static(b"test6"));
        segment.push(Bytes::from_static(b"test7"));
        segment.push(Bytes::from_static(b"test8"));
        segment.push(Bytes::from_static(b"test9"));
        assert_eq!(segment.len(), 9);

        let mut out: Vec<(Bytes, Offset)> = Vec::new();
        let _ = segment.readv((0, 0), 2, &mut out).unwrap();
        assert_eq!(
            out,
            vec![
                (Bytes::from_static(b"test1"), (0, 0)),
                (Bytes::from_static(b"test2"), (0, 1))
            ]
        );
    }

    #[test]
    fn readv_works_for_vec_of_u8() {
        let mut segment: Segment<Vec<u8>> = Segment::new();
        segment.push(vec![1u8]);
        segment.push(vec![2u8]);
        segment.push(vec![3u8]);
        segment.push(vec![4u8]);
        segment.push(vec![5u8]);
        segment.push(vec![6u8]);
        segment.push(vec![7u8]);
        segment.push(vec![8u8]);
        segment.push(vec![9u8]);
        assert_eq!(segment.len(), 9);

        let mut out: Vec<(Vec<u8>, Offset)> = Vec::new();
        let _ = segment.readv((0, 0), 2, &mut out).unwrap();
        assert_eq!(out, vec![(vec![1u8], (0, 0)), (vec![2u8], (0, 1))]);
    }

    /// fbbus: a read of up to `u64::MAX` entries (the QoS 0 read size is configurable)
    /// from past the segment's start reads to its end.
    #[test]
    fn an_unbounded_read_does_not_overflow() {
        let mut segment: Segment<Bytes> = Segment::with_offset(5);
        for i in 0..3u8 {
            segment.push(Bytes::from(vec![i]));
        }
        let mut out = Vec::new();
        match segment.readv((0, 6), u64::MAX, &mut out).unwrap() {
            SegmentPosition::Done(next) => assert_eq!(next, 8),
            SegmentPosition::Next(_) => panic!("read to the end"),
        }
        assert_eq!(out.len(), 2);
    }

    #[test]
    fn reads_cross_chunk_boundaries() {
        let mut segment: Segment<Bytes> = Segment::with_offset(10);
        for i in 0..(2 * CHUNK + 5) {
            segment.push(Bytes::from(i.to_string()));
        }
        assert_eq!(segment.len(), (2 * CHUNK + 5) as u64);
        assert_eq!(
            segment.last().unwrap(),
            Bytes::from((2 * CHUNK + 4).to_string())
        );
        let mut out = Vec::new();
        let from = 10 + CHUNK as u64 - 2;
        match segment.readv((0, from), 4, &mut out).unwrap() {
            SegmentPosition::Next(next) => assert_eq!(next, from + 4),
            SegmentPosition::Done(_) => panic!("more to read"),
        }
        let got: Vec<_> = out.iter().map(|(b, o)| (b.clone(), o.1)).collect();
        let want: Vec<_> = (0..4u64)
            .map(|k| (Bytes::from((CHUNK as u64 - 2 + k).to_string()), from + k))
            .collect();
        assert_eq!(got, want);
    }
}
