//! Parquet tables for the exports: columns built from plain vectors, written through `arrow`
//! with snappy compression (as LeRobot writes its files), atomically.

use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

use arrow_array::builder::{Float64Builder, Int64Builder, ListBuilder, StringBuilder};
use arrow_array::{
    ArrayRef, FixedSizeListArray, Float32Array, Float64Array, Int64Array, RecordBatch, StringArray,
};
use arrow_schema::{Field, Schema};
use parquet::arrow::ArrowWriter;
use parquet::basic::Compression;
use parquet::file::properties::WriterProperties;

use crate::error::{BackendError, Result};

/// A table being built, column by column.
#[derive(Default)]
pub struct Table {
    fields: Vec<Field>,
    columns: Vec<ArrayRef>,
    metadata: HashMap<String, String>,
}

fn table_err(message: &str) -> BackendError {
    BackendError::Export(format!("building a parquet table: {message}"))
}

impl Table {
    fn push(&mut self, name: &str, array: ArrayRef) {
        self.fields
            .push(Field::new(name, array.data_type().clone(), false));
        self.columns.push(array);
    }

    /// An int64 column.
    pub fn i64(&mut self, name: &str, values: Vec<i64>) {
        self.push(name, Arc::new(Int64Array::from(values)));
    }

    /// A float32 column.
    pub fn f32(&mut self, name: &str, values: Vec<f32>) {
        self.push(name, Arc::new(Float32Array::from(values)));
    }

    /// A float64 column.
    pub fn f64(&mut self, name: &str, values: Vec<f64>) {
        self.push(name, Arc::new(Float64Array::from(values)));
    }

    /// A string column.
    pub fn string(&mut self, name: &str, values: Vec<String>) {
        self.push(name, Arc::new(StringArray::from(values)));
    }

    /// A list-of-strings column.
    pub fn string_lists(&mut self, name: &str, values: &[Vec<String>]) {
        let mut b = ListBuilder::new(StringBuilder::new());
        for row in values {
            for s in row {
                b.values().append_value(s);
            }
            b.append(true);
        }
        self.push(name, Arc::new(b.finish()));
    }

    /// A list-of-float64 column (one list per row, of any length): how LeRobot's episode
    /// statistics of a numeric feature are stored.
    pub fn f64_lists(&mut self, name: &str, rows: &[Vec<f64>]) {
        let mut b = ListBuilder::new(Float64Builder::new());
        for row in rows {
            b.values().append_slice(row);
            b.append(true);
        }
        self.push(name, Arc::new(b.finish()));
    }

    /// A list-of-int64 column (one list per row).
    pub fn i64_lists(&mut self, name: &str, rows: &[Vec<i64>]) {
        let mut b = ListBuilder::new(Int64Builder::new());
        for row in rows {
            b.values().append_slice(row);
            b.append(true);
        }
        self.push(name, Arc::new(b.finish()));
    }

    /// A column of per-channel values shaped `(channels, 1, 1)` per row (nested lists): how
    /// LeRobot's episode statistics of an image feature are stored.
    pub fn f64_channel_lists(&mut self, name: &str, rows: &[Vec<f64>]) {
        let mut b = ListBuilder::new(ListBuilder::new(ListBuilder::new(Float64Builder::new())));
        for row in rows {
            for &v in row {
                let channel = b.values();
                channel.values().values().append_value(v);
                channel.values().append(true);
                channel.append(true);
            }
            b.append(true);
        }
        self.push(name, Arc::new(b.finish()));
    }

    /// A fixed-size list column (`width` values per row, row-major in `values`) of float32 or
    /// int64 items: what LeRobot's `Sequence(length=width)` features are in arrow.
    pub fn fixed_list(&mut self, name: &str, width: usize, values: ArrayRef) -> Result<()> {
        let item = Arc::new(Field::new("item", values.data_type().clone(), true));
        let size =
            i32::try_from(width).map_err(|_| table_err(&format!("{name}: width {width}")))?;
        let list = FixedSizeListArray::try_new(item, size, values, None)
            .map_err(|e| table_err(&format!("{name}: {e}")))?;
        self.push(name, Arc::new(list));
        Ok(())
    }

    /// A fixed-size list of float32.
    pub fn f32_list(&mut self, name: &str, width: usize, values: Vec<f32>) -> Result<()> {
        self.fixed_list(name, width, Arc::new(Float32Array::from(values)))
    }

    /// A fixed-size list of int64.
    pub fn i64_list(&mut self, name: &str, width: usize, values: Vec<i64>) -> Result<()> {
        self.fixed_list(name, width, Arc::new(Int64Array::from(values)))
    }

    /// A key of the schema's metadata (e.g. `pandas`, which pandas reads its index from).
    pub fn metadata(&mut self, key: &str, value: String) {
        self.metadata.insert(key.to_string(), value);
    }

    /// Write the table to `path` atomically.
    pub fn write(self, path: &Path) -> Result<()> {
        let schema = Arc::new(Schema::new_with_metadata(self.fields, self.metadata));
        let batch = RecordBatch::try_new(schema.clone(), self.columns)
            .map_err(|e| table_err(&format!("{}: {e}", path.display())))?;
        let props = WriterProperties::builder()
            .set_compression(Compression::SNAPPY)
            .build();
        let mut bytes = Vec::new();
        {
            let mut writer = ArrowWriter::try_new(&mut bytes, schema, Some(props))
                .map_err(|e| table_err(&format!("{}: {e}", path.display())))?;
            writer
                .write(&batch)
                .map_err(|e| table_err(&format!("{}: {e}", path.display())))?;
            writer
                .close()
                .map_err(|e| table_err(&format!("{}: {e}", path.display())))?;
        }
        kiwi_core::io::write_atomic(path, &bytes)?;
        Ok(())
    }
}
