//! A small builder for ONNX graphs (opset 17, IR 9): nodes, initializers, inputs and outputs
//! by name, each layer of a network emitting its own nodes (as tract's and burn-import's
//! exporters do). Weights become initializers and are never also graph inputs, so ONNX
//! Runtime can fold and fuse them.

use onnx_protobuf::attribute_proto::AttributeType;
use onnx_protobuf::tensor_proto::DataType;
use onnx_protobuf::tensor_shape_proto::{dimension, Dimension};
use onnx_protobuf::type_proto;
use onnx_protobuf::{
    AttributeProto, GraphProto, ModelProto, NodeProto, OperatorSetIdProto, StringStringEntryProto, TensorProto, TensorShapeProto,
    TypeProto, ValueInfoProto,
};

/// The ONNX IR version written (ONNX Runtime 1.31 reads IR ≤ 13; 9 goes with opset 17).
pub const IR_VERSION: i64 = 9;
/// The default-domain opset the graphs use.
pub const OPSET: i64 = 17;

/// A node attribute.
pub enum Attr<'a> {
    Int(&'a str, i64),
    Ints(&'a str, &'a [i64]),
    Float(&'a str, f32),
    Str(&'a str, &'a str),
}

impl Attr<'_> {
    fn proto(&self) -> AttributeProto {
        let mut a = AttributeProto::new();
        let (name, ty) = match self {
            Attr::Int(n, v) => {
                a.i = *v;
                (n, AttributeType::INT)
            }
            Attr::Ints(n, v) => {
                a.ints = v.to_vec();
                (n, AttributeType::INTS)
            }
            Attr::Float(n, v) => {
                a.f = *v;
                (n, AttributeType::FLOAT)
            }
            Attr::Str(n, v) => {
                a.s = v.as_bytes().to_vec();
                (n, AttributeType::STRING)
            }
        };
        a.name = name.to_string();
        a.type_ = ty.into();
        a
    }
}

/// A dimension of a graph input or output: fixed or named (dynamic).
#[derive(Debug, Clone, Copy)]
pub enum Dim<'a> {
    Fixed(usize),
    Named(&'a str),
}

/// A graph under construction.
#[derive(Debug, Default)]
pub struct Graph {
    graph: GraphProto,
    next: usize,
}

impl Graph {
    pub fn new(name: &str) -> Self {
        let mut graph = GraphProto::new();
        graph.name = name.to_string();
        Graph { graph, next: 0 }
    }

    /// A fresh value name starting with `hint`.
    pub fn fresh(&mut self, hint: &str) -> String {
        self.next += 1;
        format!("{hint}_{}", self.next)
    }

    /// Nodes so far.
    pub fn node_count(&self) -> usize {
        self.graph.node.len()
    }

    /// A float32 graph input.
    pub fn input(&mut self, name: &str, dims: &[Dim<'_>]) -> String {
        self.graph.input.push(value_info(name, dims));
        name.to_string()
    }

    /// Declare `value` a float32 graph output named `name` (an `Identity` renames it).
    pub fn output(&mut self, value: &str, name: &str, dims: &[Dim<'_>]) {
        self.node_named("Identity", &[value], &[], name);
        self.graph.output.push(value_info(name, dims));
    }

    /// A float32 initializer `[dims]` (row-major data).
    pub fn weight(&mut self, hint: &str, dims: &[usize], data: &[f32]) -> String {
        debug_assert_eq!(dims.iter().product::<usize>(), data.len(), "{hint}");
        let dims: Vec<i64> = dims.iter().map(|&d| d as i64).collect();
        self.initializer(hint, DataType::FLOAT, dims, data.iter().flat_map(|v| v.to_le_bytes()).collect())
    }

    /// A float32 scalar initializer (shape `[]`, broadcasts).
    pub fn scalar(&mut self, hint: &str, v: f32) -> String {
        self.weight(hint, &[], &[v])
    }

    /// An int64 initializer `[dims]`.
    pub fn ints(&mut self, hint: &str, data: &[i64]) -> String {
        self.initializer(hint, DataType::INT64, vec![data.len() as i64], data.iter().flat_map(|v| v.to_le_bytes()).collect())
    }

    fn initializer(&mut self, hint: &str, ty: DataType, dims: Vec<i64>, raw: Vec<u8>) -> String {
        let name = self.fresh(hint);
        let mut t = TensorProto::new();
        t.name = name.clone();
        t.data_type = ty as i32;
        t.dims = dims;
        t.raw_data = raw;
        self.graph.initializer.push(t);
        name
    }

    /// One node with one output; returns the output's name.
    pub fn node(&mut self, op: &str, inputs: &[&str], attrs: &[Attr<'_>]) -> String {
        let out = self.fresh(&op.to_lowercase());
        self.node_named(op, inputs, attrs, &out);
        out
    }

    /// One node without attributes.
    pub fn op(&mut self, op: &str, inputs: &[&str]) -> String {
        self.node(op, inputs, &[])
    }

    /// One node with `n` outputs.
    pub fn node_multi(&mut self, op: &str, inputs: &[&str], attrs: &[Attr<'_>], n: usize) -> Vec<String> {
        let outs: Vec<String> = (0..n).map(|_| self.fresh(&op.to_lowercase())).collect();
        self.push_node(op, inputs, attrs, outs.clone());
        outs
    }

    fn node_named(&mut self, op: &str, inputs: &[&str], attrs: &[Attr<'_>], out: &str) {
        self.push_node(op, inputs, attrs, vec![out.to_string()]);
    }

    fn push_node(&mut self, op: &str, inputs: &[&str], attrs: &[Attr<'_>], outputs: Vec<String>) {
        let mut node = NodeProto::new();
        node.op_type = op.to_string();
        node.name = format!("{op}_{}", self.graph.node.len());
        node.input = inputs.iter().map(|s| s.to_string()).collect();
        node.output = outputs;
        node.attribute = attrs.iter().map(Attr::proto).collect();
        self.graph.node.push(node);
    }

    /// The model: this graph, opset 17, IR 9, and `metadata` as `metadata_props`.
    pub fn into_model(self, doc: &str, metadata: &[(String, String)]) -> ModelProto {
        let mut m = ModelProto::new();
        m.ir_version = IR_VERSION;
        let mut opset = OperatorSetIdProto::new();
        opset.domain = String::new();
        opset.version = OPSET;
        m.opset_import = vec![opset];
        m.producer_name = "tcsense".into();
        m.producer_version = env!("CARGO_PKG_VERSION").into();
        m.doc_string = doc.to_string();
        m.graph = protobuf::MessageField::some(self.graph);
        m.metadata_props = metadata
            .iter()
            .map(|(k, v)| {
                let mut e = StringStringEntryProto::new();
                e.key = k.clone();
                e.value = v.clone();
                e
            })
            .collect();
        m
    }
}

fn value_info(name: &str, dims: &[Dim<'_>]) -> ValueInfoProto {
    let mut shape = TensorShapeProto::new();
    shape.dim = dims
        .iter()
        .map(|d| {
            let mut dim = Dimension::new();
            dim.value = Some(match d {
                Dim::Fixed(n) => dimension::Value::DimValue(*n as i64),
                Dim::Named(s) => dimension::Value::DimParam(s.to_string()),
            });
            dim
        })
        .collect();
    let mut tensor = type_proto::Tensor::new();
    tensor.elem_type = DataType::FLOAT as i32;
    tensor.shape = protobuf::MessageField::some(shape);
    let mut tp = TypeProto::new();
    tp.value = Some(type_proto::Value::TensorType(tensor));
    let mut vi = ValueInfoProto::new();
    vi.name = name.to_string();
    vi.type_ = protobuf::MessageField::some(tp);
    vi
}
