//! RTDE data types and values (RTDE guide, "Data types"): the exact type strings the
//! controller sends in setup replies, their big-endian sizes, and value (de)serialisation.

use super::RtdeError;

/// One RTDE field type, as named in setup replies.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub enum DataType {
    /// `BOOL`: one byte, 0 or 1.
    Bool,
    /// `UINT8`.
    Uint8,
    /// `UINT32`.
    Uint32,
    /// `UINT64`.
    Uint64,
    /// `INT32`.
    Int32,
    /// `DOUBLE`: IEEE 754 binary64.
    Double,
    /// `VECTOR3D`: three doubles.
    Vector3d,
    /// `VECTOR6D`: six doubles.
    Vector6d,
    /// `VECTOR6INT32`: six int32.
    Vector6Int32,
    /// `VECTOR6UINT32`: six uint32.
    Vector6Uint32,
}

impl DataType {
    /// Every type, for tests and tables.
    pub const ALL: [DataType; 10] = [
        DataType::Bool,
        DataType::Uint8,
        DataType::Uint32,
        DataType::Uint64,
        DataType::Int32,
        DataType::Double,
        DataType::Vector3d,
        DataType::Vector6d,
        DataType::Vector6Int32,
        DataType::Vector6Uint32,
    ];

    /// The exact wire string.
    pub fn as_str(self) -> &'static str {
        match self {
            DataType::Bool => "BOOL",
            DataType::Uint8 => "UINT8",
            DataType::Uint32 => "UINT32",
            DataType::Uint64 => "UINT64",
            DataType::Int32 => "INT32",
            DataType::Double => "DOUBLE",
            DataType::Vector3d => "VECTOR3D",
            DataType::Vector6d => "VECTOR6D",
            DataType::Vector6Int32 => "VECTOR6INT32",
            DataType::Vector6Uint32 => "VECTOR6UINT32",
        }
    }

    /// Parses a wire type string (not the `NOT_FOUND`/`IN_USE` markers).
    pub fn parse(s: &str) -> Option<DataType> {
        DataType::ALL.into_iter().find(|t| t.as_str() == s)
    }

    /// Bytes this type occupies in a data package.
    pub fn size(self) -> usize {
        match self {
            DataType::Bool | DataType::Uint8 => 1,
            DataType::Uint32 | DataType::Int32 => 4,
            DataType::Uint64 | DataType::Double => 8,
            DataType::Vector3d => 24,
            DataType::Vector6d => 48,
            DataType::Vector6Int32 | DataType::Vector6Uint32 => 24,
        }
    }
}

/// One entry of a setup reply's type list.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub enum FieldType {
    /// The name is known and has this type.
    Type(DataType),
    /// `NOT_FOUND`: the controller does not know the name.
    NotFound,
    /// `IN_USE`: another client or a fieldbus already owns this input.
    InUse,
}

impl FieldType {
    /// The exact wire string.
    pub fn as_str(self) -> &'static str {
        match self {
            FieldType::Type(t) => t.as_str(),
            FieldType::NotFound => "NOT_FOUND",
            FieldType::InUse => "IN_USE",
        }
    }

    /// Parses a wire string.
    pub fn parse(s: &str) -> Result<FieldType, RtdeError> {
        match s {
            "NOT_FOUND" => Ok(FieldType::NotFound),
            "IN_USE" => Ok(FieldType::InUse),
            other => {
                DataType::parse(other)
                    .map(FieldType::Type)
                    .ok_or_else(|| RtdeError::UnknownType {
                        name: other.to_string(),
                    })
            }
        }
    }
}

/// One field value of a data package.
#[derive(Copy, Clone, Debug, PartialEq)]
pub enum Value {
    /// `BOOL`.
    Bool(bool),
    /// `UINT8`.
    Uint8(u8),
    /// `UINT32`.
    Uint32(u32),
    /// `UINT64`.
    Uint64(u64),
    /// `INT32`.
    Int32(i32),
    /// `DOUBLE`.
    Double(f64),
    /// `VECTOR3D`.
    Vector3d([f64; 3]),
    /// `VECTOR6D`.
    Vector6d([f64; 6]),
    /// `VECTOR6INT32`.
    Vector6Int32([i32; 6]),
    /// `VECTOR6UINT32`.
    Vector6Uint32([u32; 6]),
}

impl Value {
    /// The value's type.
    pub fn data_type(&self) -> DataType {
        match self {
            Value::Bool(_) => DataType::Bool,
            Value::Uint8(_) => DataType::Uint8,
            Value::Uint32(_) => DataType::Uint32,
            Value::Uint64(_) => DataType::Uint64,
            Value::Int32(_) => DataType::Int32,
            Value::Double(_) => DataType::Double,
            Value::Vector3d(_) => DataType::Vector3d,
            Value::Vector6d(_) => DataType::Vector6d,
            Value::Vector6Int32(_) => DataType::Vector6Int32,
            Value::Vector6Uint32(_) => DataType::Vector6Uint32,
        }
    }

    /// Writes the value big-endian into `out`, which must be exactly `data_type().size()` long.
    pub fn write(&self, out: &mut [u8]) -> Result<(), RtdeError> {
        let need = self.data_type().size();
        if out.len() != need {
            return Err(RtdeError::Truncated {
                what: "data package field",
                need,
                got: out.len(),
            });
        }
        match *self {
            Value::Bool(b) => out[0] = u8::from(b),
            Value::Uint8(v) => out[0] = v,
            Value::Uint32(v) => out.copy_from_slice(&v.to_be_bytes()),
            Value::Uint64(v) => out.copy_from_slice(&v.to_be_bytes()),
            Value::Int32(v) => out.copy_from_slice(&v.to_be_bytes()),
            Value::Double(v) => out.copy_from_slice(&v.to_be_bytes()),
            Value::Vector3d(v) => {
                for (c, x) in out.chunks_exact_mut(8).zip(v) {
                    c.copy_from_slice(&x.to_be_bytes());
                }
            }
            Value::Vector6d(v) => {
                for (c, x) in out.chunks_exact_mut(8).zip(v) {
                    c.copy_from_slice(&x.to_be_bytes());
                }
            }
            Value::Vector6Int32(v) => {
                for (c, x) in out.chunks_exact_mut(4).zip(v) {
                    c.copy_from_slice(&x.to_be_bytes());
                }
            }
            Value::Vector6Uint32(v) => {
                for (c, x) in out.chunks_exact_mut(4).zip(v) {
                    c.copy_from_slice(&x.to_be_bytes());
                }
            }
        }
        Ok(())
    }

    /// Reads a value of type `t` from the start of `bytes`.
    pub fn read(t: DataType, bytes: &[u8]) -> Result<Value, RtdeError> {
        let need = t.size();
        let b = bytes.get(..need).ok_or(RtdeError::Truncated {
            what: "data package field",
            need,
            got: bytes.len(),
        })?;
        let f64_at = |i: usize| {
            let mut a = [0u8; 8];
            a.copy_from_slice(&b[i * 8..i * 8 + 8]);
            f64::from_be_bytes(a)
        };
        let u32_at = |i: usize| {
            let mut a = [0u8; 4];
            a.copy_from_slice(&b[i * 4..i * 4 + 4]);
            u32::from_be_bytes(a)
        };
        Ok(match t {
            DataType::Bool => match b[0] {
                0 => Value::Bool(false),
                1 => Value::Bool(true),
                v => return Err(RtdeError::BadBool { value: v }),
            },
            DataType::Uint8 => Value::Uint8(b[0]),
            DataType::Uint32 => Value::Uint32(u32_at(0)),
            DataType::Uint64 => {
                let mut a = [0u8; 8];
                a.copy_from_slice(b);
                Value::Uint64(u64::from_be_bytes(a))
            }
            DataType::Int32 => Value::Int32(u32_at(0) as i32),
            DataType::Double => Value::Double(f64_at(0)),
            DataType::Vector3d => Value::Vector3d([f64_at(0), f64_at(1), f64_at(2)]),
            DataType::Vector6d => Value::Vector6d(std::array::from_fn(f64_at)),
            DataType::Vector6Int32 => {
                Value::Vector6Int32(std::array::from_fn(|i| u32_at(i) as i32))
            }
            DataType::Vector6Uint32 => Value::Vector6Uint32(std::array::from_fn(u32_at)),
        })
    }
}

/// The layout of a recipe's data package: field types and their byte offsets, computed once
/// so that a real-time loop can read and write fields in place without allocating.
#[derive(Clone, Debug, PartialEq)]
pub struct Layout {
    types: Vec<DataType>,
    offsets: Vec<usize>,
    size: usize,
}

impl Layout {
    /// Builds the layout of `types` in order.
    pub fn new(types: &[DataType]) -> Self {
        let mut offsets = Vec::with_capacity(types.len());
        let mut size = 0;
        for t in types {
            offsets.push(size);
            size += t.size();
        }
        Self {
            types: types.to_vec(),
            offsets,
            size,
        }
    }

    /// Field types in order.
    pub fn types(&self) -> &[DataType] {
        &self.types
    }

    /// Total bytes of the values (without recipe id).
    pub fn size(&self) -> usize {
        self.size
    }

    fn field(&self, index: usize, want: DataType) -> Result<(usize, usize), RtdeError> {
        let t = *self.types.get(index).ok_or(RtdeError::FieldIndex {
            index,
            count: self.types.len(),
        })?;
        if t != want {
            return Err(RtdeError::FieldType {
                index,
                expected: want.as_str(),
                found: t.as_str(),
            });
        }
        Ok((self.offsets[index], t.size()))
    }

    /// Reads field `index` of `values` (the package payload after any recipe id).
    pub fn get(&self, values: &[u8], index: usize) -> Result<Value, RtdeError> {
        let t = *self.types.get(index).ok_or(RtdeError::FieldIndex {
            index,
            count: self.types.len(),
        })?;
        self.check_len(values)?;
        Value::read(t, &values[self.offsets[index]..])
    }

    /// Reads a `DOUBLE` field.
    pub fn get_f64(&self, values: &[u8], index: usize) -> Result<f64, RtdeError> {
        let (o, _) = self.field(index, DataType::Double)?;
        self.check_len(values)?;
        let mut a = [0u8; 8];
        a.copy_from_slice(&values[o..o + 8]);
        Ok(f64::from_be_bytes(a))
    }

    /// Reads a `VECTOR6D` field.
    pub fn get_vec6(&self, values: &[u8], index: usize) -> Result<[f64; 6], RtdeError> {
        let (o, _) = self.field(index, DataType::Vector6d)?;
        self.check_len(values)?;
        Ok(std::array::from_fn(|i| {
            let mut a = [0u8; 8];
            a.copy_from_slice(&values[o + 8 * i..o + 8 * i + 8]);
            f64::from_be_bytes(a)
        }))
    }

    /// Reads an `INT32` field.
    pub fn get_i32(&self, values: &[u8], index: usize) -> Result<i32, RtdeError> {
        let (o, _) = self.field(index, DataType::Int32)?;
        self.check_len(values)?;
        let mut a = [0u8; 4];
        a.copy_from_slice(&values[o..o + 4]);
        Ok(i32::from_be_bytes(a))
    }

    /// Reads a `UINT32` field.
    pub fn get_u32(&self, values: &[u8], index: usize) -> Result<u32, RtdeError> {
        let (o, _) = self.field(index, DataType::Uint32)?;
        self.check_len(values)?;
        let mut a = [0u8; 4];
        a.copy_from_slice(&values[o..o + 4]);
        Ok(u32::from_be_bytes(a))
    }

    /// Writes field `index` into `values` in place; the value's type must match the layout.
    pub fn set(&self, values: &mut [u8], index: usize, value: Value) -> Result<(), RtdeError> {
        let (o, n) = self.field(index, value.data_type())?;
        self.check_len(values)?;
        value.write(&mut values[o..o + n])
    }

    /// Decodes every field of `values`.
    pub fn decode_all(&self, values: &[u8]) -> Result<Vec<Value>, RtdeError> {
        self.check_len(values)?;
        self.types
            .iter()
            .zip(&self.offsets)
            .map(|(t, o)| Value::read(*t, &values[*o..]))
            .collect()
    }

    /// Encodes `fields` (which must match the layout's types) into a fresh buffer.
    pub fn encode_all(&self, fields: &[Value]) -> Result<Vec<u8>, RtdeError> {
        if fields.len() != self.types.len() {
            return Err(RtdeError::FieldCount {
                expected: self.types.len(),
                got: fields.len(),
            });
        }
        let mut out = vec![0u8; self.size];
        for (i, v) in fields.iter().enumerate() {
            self.set(&mut out, i, *v)?;
        }
        Ok(out)
    }

    fn check_len(&self, values: &[u8]) -> Result<(), RtdeError> {
        if values.len() != self.size {
            return Err(RtdeError::PackageSize {
                expected: self.size,
                got: values.len(),
            });
        }
        Ok(())
    }
}
