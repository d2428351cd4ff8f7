//! Hand-written protobuf codecs of the two messages of `MdWorker.Step`, the hot path of the
//! coupling: `StepBatch` (with its `BoxWork` items) and `StepResults` (with its `BoxResult`
//! items). The generated types keep every repeated field in its own `Vec`, so a batch of 20,000
//! boxes costs 20,000 to 40,000 heap allocations each way, and prost encodes and decodes packed
//! doubles one call per value. These types hold the fixed-size fields inline (no allocation per
//! box) and move packed doubles as blocks.
//!
//! The wire format is exactly `mscale.coupling.v1` (coupling.proto is unchanged, and
//! build.rs maps the two messages here with `extern_path`): the same bytes as prost's encoding
//! of the generated types (proto3 defaults omitted, doubles packed, fields in number order),
//! and decoding accepts any valid encoding (fields in any order, repeated fields split or
//! unpacked, unknown fields skipped). Tests compare both ways against the generated types.
//!
//! A repeated double keeps at most the values the protocol defines (9, 6 or 3) and counts
//! them all, so the receiver can still refuse a wrong count naming the field.

use prost::DecodeError;
use prost::bytes::{Buf, BufMut};
use prost::encoding::{
    DecodeContext, WireType, check_wire_type, decode_key, decode_varint, encode_key, encode_varint, encoded_len_varint, key_len, skip_field,
};

/// A repeated double of at most `N` kept values and the count seen on the wire.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Doubles<const N: usize> {
    /// The first `N` values (zeros beyond `len`).
    pub values: [f64; N],
    /// How many values the field had (may exceed `N` for a malformed message).
    pub len: usize,
}

impl<const N: usize> Default for Doubles<N> {
    fn default() -> Self {
        Doubles { values: [0.0; N], len: 0 }
    }
}

impl<const N: usize> Doubles<N> {
    /// All `N` values.
    pub fn full(values: [f64; N]) -> Self {
        Doubles { values, len: N }
    }

    /// The kept values.
    pub fn as_slice(&self) -> &[f64] {
        &self.values[..self.len.min(N)]
    }

    fn push(&mut self, v: f64) {
        if self.len < N {
            self.values[self.len] = v;
        }
        self.len += 1;
    }

    fn encoded_len(&self, tag: u32) -> usize {
        let n = self.len.min(N);
        if n == 0 { 0 } else { key_len(tag) + encoded_len_varint(8 * n as u64) + 8 * n }
    }

    /// Packed, as prost writes a proto3 `repeated double` (nothing when empty).
    fn encode(&self, tag: u32, buf: &mut impl BufMut) {
        let n = self.len.min(N);
        if n == 0 {
            return;
        }
        encode_key(tag, WireType::LengthDelimited, buf);
        encode_varint(8 * n as u64, buf);
        if n > 16 {
            self.values[..n].iter().for_each(|v| buf.put_f64_le(*v));
            return;
        }
        // One block write instead of one call per value.
        let mut block = [0u8; 8 * 16];
        for (k, v) in self.values[..n].iter().enumerate() {
            block[8 * k..8 * k + 8].copy_from_slice(&v.to_le_bytes());
        }
        buf.put_slice(&block[..8 * n]);
    }

    /// Packed (any number of times) or unpacked values.
    fn merge(&mut self, wire_type: WireType, buf: &mut impl Buf) -> Result<(), DecodeError> {
        if wire_type == WireType::LengthDelimited {
            let len = decode_varint(buf)?;
            if len > buf.remaining() as u64 {
                return Err(DecodeError::new("buffer underflow"));
            }
            if len % 8 != 0 {
                return Err(DecodeError::new("packed doubles: length is not a multiple of 8"));
            }
            for _ in 0..len / 8 {
                self.push(buf.get_f64_le());
            }
            Ok(())
        } else {
            self.push(double(wire_type, buf)?);
            Ok(())
        }
    }
}

fn uint64(wire_type: WireType, buf: &mut impl Buf) -> Result<u64, DecodeError> {
    check_wire_type(WireType::Varint, wire_type)?;
    decode_varint(buf)
}

fn int32(wire_type: WireType, buf: &mut impl Buf) -> Result<i32, DecodeError> {
    // As prost: the varint truncated to 32 bits.
    Ok(uint64(wire_type, buf)? as i32)
}

fn double(wire_type: WireType, buf: &mut impl Buf) -> Result<f64, DecodeError> {
    check_wire_type(WireType::SixtyFourBit, wire_type)?;
    if buf.remaining() < 8 {
        return Err(DecodeError::new("buffer underflow"));
    }
    Ok(buf.get_f64_le())
}

fn put_uint64(tag: u32, v: u64, buf: &mut impl BufMut) {
    if v != 0 {
        encode_key(tag, WireType::Varint, buf);
        encode_varint(v, buf);
    }
}

fn len_uint64(tag: u32, v: u64) -> usize {
    if v != 0 { key_len(tag) + encoded_len_varint(v) } else { 0 }
}

fn put_int32(tag: u32, v: i32, buf: &mut impl BufMut) {
    // Negative values sign-extend to 10 bytes, as prost writes them.
    put_uint64(tag, v as u64, buf);
}

fn len_int32(tag: u32, v: i32) -> usize {
    len_uint64(tag, v as u64)
}

fn put_double(tag: u32, v: f64, buf: &mut impl BufMut) {
    // As prost: a value equal to 0.0 (either sign) is the default and is not written.
    if v != 0.0 {
        encode_key(tag, WireType::SixtyFourBit, buf);
        buf.put_f64_le(v);
    }
}

fn len_double(tag: u32, v: f64) -> usize {
    if v != 0.0 { key_len(tag) + 8 } else { 0 }
}

/// `mscale.coupling.v1.BoxWork` (see coupling.proto for the fields' meaning and units).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct WorkItem {
    pub point_id: u64,
    pub velocity_gradient: Doubles<9>,
    pub steps: u64,
    pub dt_ps: f64,
    pub energy_to_add_ev: f64,
    /// A `StressSampling` value.
    pub stress_sampling: i32,
}

impl prost::Message for WorkItem {
    fn encode_raw(&self, buf: &mut impl BufMut) {
        put_uint64(1, self.point_id, buf);
        self.velocity_gradient.encode(2, buf);
        put_uint64(3, self.steps, buf);
        put_double(4, self.dt_ps, buf);
        put_double(5, self.energy_to_add_ev, buf);
        put_int32(6, self.stress_sampling, buf);
    }

    fn merge_field(&mut self, tag: u32, wire_type: WireType, buf: &mut impl Buf, ctx: DecodeContext) -> Result<(), DecodeError> {
        match tag {
            1 => self.point_id = uint64(wire_type, buf)?,
            2 => self.velocity_gradient.merge(wire_type, buf)?,
            3 => self.steps = uint64(wire_type, buf)?,
            4 => self.dt_ps = double(wire_type, buf)?,
            5 => self.energy_to_add_ev = double(wire_type, buf)?,
            6 => self.stress_sampling = int32(wire_type, buf)?,
            _ => skip_field(wire_type, tag, buf, ctx)?,
        }
        Ok(())
    }

    fn encoded_len(&self) -> usize {
        len_uint64(1, self.point_id)
            + self.velocity_gradient.encoded_len(2)
            + len_uint64(3, self.steps)
            + len_double(4, self.dt_ps)
            + len_double(5, self.energy_to_add_ev)
            + len_int32(6, self.stress_sampling)
    }

    fn clear(&mut self) {
        *self = Self::default();
    }
}

/// `mscale.coupling.v1.BoxResult`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ResultItem {
    pub point_id: u64,
    pub stress_gpa: Doubles<6>,
    pub potential_energy_ev: f64,
    pub kinetic_energy_ev: f64,
    pub temperature_k: f64,
    pub lengths: Doubles<3>,
    pub neighbor_rebuilds: u64,
    pub energy_shortfall_ev: f64,
    pub total_steps: u64,
    pub wraps: u64,
    /// A `StressSampling` value.
    pub stress_sampling: i32,
}

impl prost::Message for ResultItem {
    fn encode_raw(&self, buf: &mut impl BufMut) {
        put_uint64(1, self.point_id, buf);
        self.stress_gpa.encode(2, buf);
        put_double(3, self.potential_energy_ev, buf);
        put_double(4, self.kinetic_energy_ev, buf);
        put_double(5, self.temperature_k, buf);
        self.lengths.encode(6, buf);
        put_uint64(7, self.neighbor_rebuilds, buf);
        put_double(8, self.energy_shortfall_ev, buf);
        put_uint64(9, self.total_steps, buf);
        put_uint64(10, self.wraps, buf);
        put_int32(11, self.stress_sampling, buf);
    }

    fn merge_field(&mut self, tag: u32, wire_type: WireType, buf: &mut impl Buf, ctx: DecodeContext) -> Result<(), DecodeError> {
        match tag {
            1 => self.point_id = uint64(wire_type, buf)?,
            2 => self.stress_gpa.merge(wire_type, buf)?,
            3 => self.potential_energy_ev = double(wire_type, buf)?,
            4 => self.kinetic_energy_ev = double(wire_type, buf)?,
            5 => self.temperature_k = double(wire_type, buf)?,
            6 => self.lengths.merge(wire_type, buf)?,
            7 => self.neighbor_rebuilds = uint64(wire_type, buf)?,
            8 => self.energy_shortfall_ev = double(wire_type, buf)?,
            9 => self.total_steps = uint64(wire_type, buf)?,
            10 => self.wraps = uint64(wire_type, buf)?,
            11 => self.stress_sampling = int32(wire_type, buf)?,
            _ => skip_field(wire_type, tag, buf, ctx)?,
        }
        Ok(())
    }

    fn encoded_len(&self) -> usize {
        len_uint64(1, self.point_id)
            + self.stress_gpa.encoded_len(2)
            + len_double(3, self.potential_energy_ev)
            + len_double(4, self.kinetic_energy_ev)
            + len_double(5, self.temperature_k)
            + self.lengths.encoded_len(6)
            + len_uint64(7, self.neighbor_rebuilds)
            + len_double(8, self.energy_shortfall_ev)
            + len_uint64(9, self.total_steps)
            + len_uint64(10, self.wraps)
            + len_int32(11, self.stress_sampling)
    }

    fn clear(&mut self) {
        *self = Self::default();
    }
}

fn len_items<M: prost::Message>(tag: u32, items: &[M]) -> usize {
    key_len(tag) * items.len()
        + items
            .iter()
            .map(|m| {
                let l = m.encoded_len();
                encoded_len_varint(l as u64) + l
            })
            .sum::<usize>()
}

/// Longest encoding of an item with its key and length (a `ResultItem` takes at most 167 bytes).
const ITEM_MAX: usize = 256;

/// Repeated message field `tag`: each item is encoded on the stack and copied into `buf` in one
/// write (a `BytesMut` checks its capacity on every write, and varints write byte by byte).
fn put_items<M: prost::Message>(tag: u32, items: &[M], buf: &mut impl BufMut) {
    for m in items {
        let len = m.encoded_len();
        if len + 12 > ITEM_MAX {
            encode_key(tag, WireType::LengthDelimited, buf);
            encode_varint(len as u64, buf);
            m.encode_raw(buf);
            continue;
        }
        let mut block = [0u8; ITEM_MAX];
        let mut w: &mut [u8] = &mut block;
        encode_key(tag, WireType::LengthDelimited, &mut w);
        encode_varint(len as u64, &mut w);
        m.encode_raw(&mut w);
        let used = ITEM_MAX - w.len();
        buf.put_slice(&block[..used]);
    }
}

/// One item of a repeated message field. When the item lies in one contiguous chunk of `buf`
/// (always, for tonic's decode buffer) it is parsed from a plain slice, which is much cheaper
/// to read from than a `BytesMut`. The vector is sized from the first item, so it does not grow
/// by doubling (copying) through a batch.
fn merge_item<M: prost::Message + Default>(
    wire_type: WireType,
    items: &mut Vec<M>,
    buf: &mut impl Buf,
    ctx: DecodeContext,
) -> Result<(), DecodeError> {
    check_wire_type(WireType::LengthDelimited, wire_type)?;
    let len = decode_varint(buf)?;
    if len > buf.remaining() as u64 {
        return Err(DecodeError::new("buffer underflow"));
    }
    let len = len as usize;
    if items.is_empty() {
        items.reserve(buf.remaining() / (len + 2).max(16) + 1);
    }
    let mut m = M::default();
    let chunk = buf.chunk();
    if chunk.len() >= len {
        let mut s: &[u8] = &chunk[..len];
        while !s.is_empty() {
            let (tag, wt) = decode_key(&mut s)?;
            m.merge_field(tag, wt, &mut s, ctx.clone())?;
        }
        buf.advance(len);
    } else {
        let mut t = buf.take(len);
        while t.has_remaining() {
            let (tag, wt) = decode_key(&mut t)?;
            m.merge_field(tag, wt, &mut t, ctx.clone())?;
        }
    }
    items.push(m);
    Ok(())
}

/// `mscale.coupling.v1.StepBatch`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StepBatch {
    pub session: u64,
    pub step: u64,
    pub work: Vec<WorkItem>,
}

impl prost::Message for StepBatch {
    fn encode_raw(&self, buf: &mut impl BufMut) {
        put_uint64(1, self.session, buf);
        put_uint64(2, self.step, buf);
        put_items(3, &self.work, buf);
    }

    fn merge_field(&mut self, tag: u32, wire_type: WireType, buf: &mut impl Buf, ctx: DecodeContext) -> Result<(), DecodeError> {
        match tag {
            1 => self.session = uint64(wire_type, buf)?,
            2 => self.step = uint64(wire_type, buf)?,
            3 => merge_item(wire_type, &mut self.work, buf, ctx)?,
            _ => skip_field(wire_type, tag, buf, ctx)?,
        }
        Ok(())
    }

    fn encoded_len(&self) -> usize {
        len_uint64(1, self.session) + len_uint64(2, self.step) + len_items(3, &self.work)
    }

    fn clear(&mut self) {
        self.session = 0;
        self.step = 0;
        self.work.clear();
    }
}

/// `mscale.coupling.v1.StepResults`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StepResults {
    pub step: u64,
    pub results: Vec<ResultItem>,
    pub compute_seconds: f64,
}

impl prost::Message for StepResults {
    fn encode_raw(&self, buf: &mut impl BufMut) {
        put_uint64(1, self.step, buf);
        put_items(2, &self.results, buf);
        put_double(3, self.compute_seconds, buf);
    }

    fn merge_field(&mut self, tag: u32, wire_type: WireType, buf: &mut impl Buf, ctx: DecodeContext) -> Result<(), DecodeError> {
        match tag {
            1 => self.step = uint64(wire_type, buf)?,
            2 => merge_item(wire_type, &mut self.results, buf, ctx)?,
            3 => self.compute_seconds = double(wire_type, buf)?,
            _ => skip_field(wire_type, tag, buf, ctx)?,
        }
        Ok(())
    }

    fn encoded_len(&self) -> usize {
        len_uint64(1, self.step) + len_items(2, &self.results) + len_double(3, self.compute_seconds)
    }

    fn clear(&mut self) {
        self.step = 0;
        self.results.clear();
        self.compute_seconds = 0.0;
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    //! Against the types prost generates from coupling.proto (`generated::*`, built by
    //! build.rs without the `extern_path` mapping).
    use super::*;
    use crate::coupling::v1 as pb;
    use prost::Message;

    /// A deterministic pseudo-random stream (xorshift) of awkward values.
    struct Values(u64);
    impl Values {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            self.0
        }
        fn f(&mut self) -> f64 {
            match self.next() % 7 {
                0 => 0.0,
                1 => -0.0,
                2 => f64::NAN,
                3 => -1e300,
                4 => f64::from_bits(self.next()),
                _ => (self.next() % 2000) as f64 / 7.0 - 100.0,
            }
        }
        fn u(&mut self) -> u64 {
            match self.next() % 4 {
                0 => 0,
                1 => u64::MAX,
                _ => self.next() >> (self.next() % 64),
            }
        }
        fn i(&mut self) -> i32 {
            [0, 1, -1, 7, i32::MIN][(self.next() % 5) as usize]
        }
    }

    fn work(v: &mut Values) -> (WorkItem, pb::BoxWork) {
        let g: [f64; 9] = std::array::from_fn(|_| v.f());
        let n = (v.next() % 10) as usize; // 0..=9 values
        let (id, steps, dt, e, s) = (v.u(), v.u(), v.f(), v.f(), v.i());
        let mut vg = Doubles::<9>::default();
        g[..n].iter().for_each(|x| vg.push(*x));
        (
            WorkItem { point_id: id, velocity_gradient: vg, steps, dt_ps: dt, energy_to_add_ev: e, stress_sampling: s },
            pb::BoxWork { point_id: id, velocity_gradient: g[..n].to_vec(), steps, dt_ps: dt, energy_to_add_ev: e, stress_sampling: s },
        )
    }

    fn result(v: &mut Values) -> (ResultItem, pb::BoxResult) {
        let s: [f64; 6] = std::array::from_fn(|_| v.f());
        let l: [f64; 3] = std::array::from_fn(|_| v.f());
        let (ns, nl) = ((v.next() % 7) as usize, (v.next() % 4) as usize);
        let (mut sd, mut ld) = (Doubles::<6>::default(), Doubles::<3>::default());
        s[..ns].iter().for_each(|x| sd.push(*x));
        l[..nl].iter().for_each(|x| ld.push(*x));
        let (id, pe, ke, t, nr, sh, ts, w, ss) = (v.u(), v.f(), v.f(), v.f(), v.u(), v.f(), v.u(), v.u(), v.i());
        (
            ResultItem {
                point_id: id,
                stress_gpa: sd,
                potential_energy_ev: pe,
                kinetic_energy_ev: ke,
                temperature_k: t,
                lengths: ld,
                neighbor_rebuilds: nr,
                energy_shortfall_ev: sh,
                total_steps: ts,
                wraps: w,
                stress_sampling: ss,
            },
            pb::BoxResult {
                point_id: id,
                stress_gpa: s[..ns].to_vec(),
                potential_energy_ev: pe,
                kinetic_energy_ev: ke,
                temperature_k: t,
                lengths: l[..nl].to_vec(),
                neighbor_rebuilds: nr,
                energy_shortfall_ev: sh,
                total_steps: ts,
                wraps: w,
                stress_sampling: ss,
            },
        )
    }

    /// Bitwise equality (NaN payloads and the sign of zero included), via the encodings.
    fn same<M: Message>(a: &M, b: &M) -> bool {
        a.encode_to_vec() == b.encode_to_vec()
    }

    #[test]
    fn items_encode_to_the_bytes_prost_writes_and_decode_back() {
        let mut v = Values(0x9e37_79b9_7f4a_7c15);
        for _ in 0..2000 {
            let (fast, generated) = work(&mut v);
            let bytes = generated.encode_to_vec();
            assert_eq!(fast.encode_to_vec(), bytes, "{generated:?}");
            assert_eq!(fast.encoded_len(), bytes.len());
            let back = WorkItem::decode(&bytes[..]).unwrap();
            assert!(same(&back, &fast), "{back:?} vs {fast:?}");
            let (fast, generated) = result(&mut v);
            let bytes = generated.encode_to_vec();
            assert_eq!(fast.encode_to_vec(), bytes, "{generated:?}");
            assert_eq!(fast.encoded_len(), bytes.len());
            assert!(same(&ResultItem::decode(&bytes[..]).unwrap(), &fast));
        }
    }

    #[test]
    fn batches_encode_as_repeated_messages_and_decode_back() {
        let mut v = Values(42);
        let items: Vec<(WorkItem, pb::BoxWork)> = (0..300).map(|_| work(&mut v)).collect();
        let batch = StepBatch { session: 3, step: 99, work: items.iter().map(|p| p.0).collect() };
        // What prost writes for the generated StepBatch: fields 1, 2, then each item as field 3.
        let mut want = Vec::new();
        prost::encoding::uint64::encode(1, &3, &mut want);
        prost::encoding::uint64::encode(2, &99, &mut want);
        for (_, g) in &items {
            prost::encoding::message::encode(3, g, &mut want);
        }
        assert_eq!(batch.encode_to_vec(), want);
        assert_eq!(batch.encoded_len(), want.len());
        assert!(same(&StepBatch::decode(&want[..]).unwrap(), &batch));
        // From a buffer in pieces (items across chunk boundaries take the slow path).
        for cut in [1, 17, 1000, want.len() / 2, want.len() - 3] {
            let pieces = prost::bytes::Buf::chain(&want[..cut], &want[cut..]);
            assert!(same(&StepBatch::decode(pieces).unwrap(), &batch), "cut at {cut}");
        }

        let rs: Vec<(ResultItem, pb::BoxResult)> = (0..300).map(|_| result(&mut v)).collect();
        let res = StepResults { step: 7, results: rs.iter().map(|p| p.0).collect(), compute_seconds: 0.25 };
        let mut want = Vec::new();
        prost::encoding::uint64::encode(1, &7, &mut want);
        for (_, g) in &rs {
            prost::encoding::message::encode(2, g, &mut want);
        }
        prost::encoding::double::encode(3, &0.25, &mut want);
        assert_eq!(res.encode_to_vec(), want);
        assert!(same(&StepResults::decode(&want[..]).unwrap(), &res));
    }

    #[test]
    fn any_valid_encoding_decodes() {
        // Fields out of order, the gradient unpacked and split over two packed runs, an
        // unknown field of each wire type, a scalar given twice (the last wins).
        let mut b = Vec::new();
        prost::encoding::double::encode(4, &0.001, &mut b);
        prost::encoding::double::encode_packed(2, &[1.0, 2.0, 3.0, 4.0], &mut b);
        prost::encoding::uint64::encode(99, &5, &mut b);
        prost::encoding::string::encode(98, &"x".to_string(), &mut b);
        prost::encoding::fixed32::encode(97, &5, &mut b);
        prost::encoding::double::encode_repeated(2, &[5.0, 6.0], &mut b);
        prost::encoding::double::encode_packed(2, &[7.0, 8.0, 9.0], &mut b);
        prost::encoding::uint64::encode(1, &11, &mut b);
        prost::encoding::uint64::encode(1, &12, &mut b);
        prost::encoding::int32::encode(6, &1, &mut b);
        let w = WorkItem::decode(&b[..]).unwrap();
        assert_eq!(w.point_id, 12);
        assert_eq!(w.velocity_gradient, Doubles::full([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0]));
        assert_eq!((w.dt_ps, w.stress_sampling), (0.001, 1));
        let g = pb::BoxWork::decode(&b[..]).unwrap();
        assert_eq!(g.velocity_gradient, w.velocity_gradient.as_slice());
        // Too many values are counted (for the receiver to refuse), not kept.
        let mut b = Vec::new();
        prost::encoding::double::encode_packed(2, &[1.0; 11], &mut b);
        let w = WorkItem::decode(&b[..]).unwrap();
        assert_eq!((w.velocity_gradient.len, w.velocity_gradient.as_slice().len()), (11, 9));
    }

    #[test]
    fn malformed_input_is_an_error_not_a_panic() {
        let mut v = Values(7);
        let batch = StepBatch { session: 1, step: 2, work: (0..20).map(|_| work(&mut v).0).collect() };
        let bytes = batch.encode_to_vec();
        for cut in 0..bytes.len() {
            // Every truncation either fails or (at an item boundary) decodes fewer items.
            if let Ok(b) = StepBatch::decode(&bytes[..cut]) {
                assert!(b.work.len() <= batch.work.len());
            }
        }
        // A packed double run whose length is not a multiple of 8.
        let b = [0x12, 0x03, 0, 0, 0];
        assert!(WorkItem::decode(&b[..]).is_err());
        // A double given as a varint.
        let b = [0x20, 0x01];
        assert!(WorkItem::decode(&b[..]).is_err());
    }
}
