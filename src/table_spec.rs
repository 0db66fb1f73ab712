//! The declaration of a table: its name, purpose and columns with their types, units and
//! meanings. Plain data, so that a kernel can own the spec of the rows it builds (the report's
//! diagnosis tables); `crate::io::tables` turns a spec into an Arrow schema and a JSON schema
//! and writes the file.

/// Logical column types used in our tables (a small, pandas-friendly subset of Arrow's).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Col {
    Utf8,
    Int32,
    Int64,
    Float64,
    Bool,
    /// `list<float64>`: a spectrum or shape per row.
    ListF64,
    /// `list<int64>`: node ids aligned with a shape list.
    ListI64,
}

/// One column of a table.
#[derive(Debug, Clone, Copy)]
pub struct ColumnSpec {
    pub name: &'static str,
    pub ty: Col,
    pub nullable: bool,
    /// Unit (SI or derived), `""` for dimensionless/none.
    pub unit: &'static str,
    pub doc: &'static str,
}

/// A table: its file name, purpose and columns.
#[derive(Debug, Clone, Copy)]
pub struct TableSpec {
    pub name: &'static str,
    pub doc: &'static str,
    pub columns: &'static [ColumnSpec],
    /// True when the table may carry further columns not listed (e.g. extra sheet columns).
    pub open: bool,
}

/// A column spec in one line (for the table constants of every stage).
pub const fn c(
    name: &'static str,
    ty: Col,
    nullable: bool,
    unit: &'static str,
    doc: &'static str,
) -> ColumnSpec {
    ColumnSpec {
        name,
        ty,
        nullable,
        unit,
        doc,
    }
}
