//! Compiles every `shaders/*.wgsl` to SPIR-V with naga and writes a kernel table.
//!
//! For each shader file we emit one SPIR-V module (all its entry points) and, for every entry
//! point, a `KernelInfo` with its workgroup size, the storage bindings it reads and writes (from
//! naga's own use analysis, so the recorder's barriers follow what the kernel really touches,
//! a binding the module declares `read_write` counting as written, as the validation layer
//! counts it),
//! the size of its push constants and the device features it needs. A broken shader stops the
//! build with naga's message, which names the file, line and column.
//!
//! Texel buffers: WGSL has no type for them, so a kernel declares a read-only view of a tensor
//! as vec4s through a storage texel buffer as `var x: texture_storage_1d<rgba32float, read>;`
//! and reads element `i` with `textureLoad(x, i)`; this step makes every such image a buffer
//! image (SPIR-V `Dim Buffer`, capability `ImageBuffer`), and the recorder binds the tensor
//! through a `VkBufferView`. On lavapipe a texel fetch is a branch-free gather where a storage
//! buffer read is a loop over the lanes with a bounds check each (docs/decisions/kernels.md).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use naga::back::spv;
use naga::valid::{Capabilities, GlobalUse, ShaderStages, SubgroupOperationSet, ValidationFlags};

fn main() {
    let shader_dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shaders");
    let out_dir = PathBuf::from(std::env::var("OUT_DIR").unwrap());
    println!("cargo:rerun-if-changed={}", shader_dir.display());

    let mut files: Vec<PathBuf> = std::fs::read_dir(&shader_dir)
        .expect("shaders/ folder is missing")
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "wgsl"))
        .collect();
    files.sort();

    let mut table = String::new();
    let mut consts = String::new();
    let mut modules = String::new();
    let mut errors = Vec::new();
    let mut kernel_index = 0usize;
    let mut flags: Vec<(String, u32, String)> = Vec::new();
    let mut layouts: Vec<PushLayout> = Vec::new();
    // (struct name, push-constant type, binding names, where it comes from), and the aliases
    // of the kernels that share one.
    let mut arg_structs: Vec<(String, String, Vec<String>, String)> = Vec::new();
    let mut args_aliases = String::new();

    let mut units = Vec::new();
    for path in &files {
        println!("cargo:rerun-if-changed={}", path.display());
        match std::fs::read_to_string(path) {
            Ok(source) => {
                match expand_includes(&shader_dir, path, &source).and_then(|s| variants(path, &s)) {
                    Ok(list) => units.extend(list),
                    Err(e) => errors.push(e),
                }
            }
            Err(e) => errors.push(format!("{}: {e}", path.display())),
        }
    }

    for (module_index, (path, stem, source)) in units.iter().enumerate() {
        match compile(&shader_dir, path, source) {
            Ok((words, kernels, module_flags, layout)) => {
                if let Some(l) = layout {
                    match layouts.iter().find(|o: &&PushLayout| o.rust_name == l.rust_name) {
                        Some(o) if *o != l => errors.push(format!(
                            "{}: struct {} is laid out differently in shaders/{stem}.wgsl (a variant?)",
                            l.declared_in, l.rust_name
                        )),
                        Some(_) => {}
                        None => layouts.push(l),
                    }
                }
                for (name, value) in module_flags {
                    match flags.iter().find(|(n, _, _)| *n == name) {
                        Some((_, v, first)) if *v != value => errors.push(format!(
                            "shaders/{stem}.wgsl: {name} = {value}, but shaders/{first}.wgsl has {v}"
                        )),
                        Some(_) => {}
                        None => flags.push((name, value, stem.clone())),
                    }
                }
                let spv_path = out_dir.join(format!("{stem}.spv"));
                std::fs::write(&spv_path, bytemuck_words(&words)).unwrap();
                writeln!(
                    modules,
                    "    ModuleSource {{ name: {stem:?}, spirv: include_bytes!({:?}) }},",
                    spv_path.display().to_string()
                )
                .unwrap();
                for k in kernels {
                    let const_name = format!("{}_{}", stem, k.entry).to_uppercase();
                    let params = k.params.as_ref().map(|p| format!("params::{p}")).unwrap_or("()".into());
                    // The argument struct: one per list of binding names and push-constant type
                    // (the kernels one op chooses between), named after the first kernel that has
                    // it; every other kernel with that list gets an alias.
                    let names: Vec<String> = k.bindings.iter().map(|(_, _, n, _)| n.clone()).collect();
                    let own = format!("{}Args", camel(&format!("{stem}_{}", k.entry)));
                    let shared = arg_structs.iter().find(|(_, p, n, _)| *p == params && *n == names);
                    let canonical = match shared {
                        Some((c, _, _, _)) => {
                            writeln!(args_aliases, "/// The buffers of `shaders/{stem}.wgsl`, `{}` (the same as [`{c}`]).\npub type {own}<'a> = {c}<'a>;", k.entry).unwrap();
                            c.clone()
                        }
                        None => {
                            arg_structs.push((
                                own.clone(),
                                params.clone(),
                                names,
                                format!("shaders/{stem}.wgsl`, entry point `{}", k.entry),
                            ));
                            own
                        }
                    };
                    // The mirror is as large as the shader's push constants, or the build stops.
                    writeln!(
                        consts,
                        "const _: () = assert!(std::mem::size_of::<{params}>() == {});",
                        k.push_bytes
                    )
                    .unwrap();
                    writeln!(
                        consts,
                        "/// `shaders/{stem}.wgsl`, entry point `{}`.\npub const {const_name}: Kernel<{params}, args::{canonical}<'static>> = Kernel::new({kernel_index});",
                        k.entry
                    )
                    .unwrap();
                    let bindings: Vec<String> = k
                        .bindings
                        .iter()
                        .map(|(b, w, name, texel)| {
                            format!(
                                "BindingInfo {{ binding: {b}, writes: {w}, name: {name:?}, texel: {texel} }}"
                            )
                        })
                        .collect();
                    writeln!(
                        table,
                        "    KernelInfo {{ module: {module_index}, file: {stem:?}, entry: {:?}, workgroup_size: {:?}, bindings: &[{}], push_bytes: {}, shared_bytes: {}, needs: Needs {{ f16: {}, float_atomics: {}, coop_matrix: {}, memory_model: {}, subgroups: {}, subgroup_ops: {:#x}, subgroup_size: {:?} }} }},",
                        k.entry,
                        k.workgroup_size,
                        bindings.join(", "),
                        k.push_bytes,
                        k.shared_bytes,
                        k.needs.f16,
                        k.needs.float_atomics,
                        k.needs.coop_matrix,
                        k.needs.memory_model,
                        k.needs.subgroup_ops != 0,
                        k.needs.subgroup_ops,
                        k.subgroup_size,
                    )
                    .unwrap();
                    kernel_index += 1;
                }
            }
            Err(message) => errors.push(message),
        }
    }

    errors.dedup(); // variants of one file fail alike
    if !errors.is_empty() {
        for e in &errors {
            eprintln!("{e}");
        }
        panic!("{} shader(s) failed to compile; see the messages above", errors.len());
    }

    for (name, value, stem) in &flags {
        writeln!(consts, "/// `{name}` of `shaders/{stem}.wgsl` (and every shader that shares it).\npub const {name}: u32 = {value};").unwrap();
    }
    consts.push_str(&op_tables(&flags));
    layouts.sort_by(|a, b| a.rust_name.cmp(&b.rust_name));
    let args: String =
        arg_structs.iter().map(|(name, _, fields, from)| args_struct(name, fields, from)).collect();
    let structs: String = layouts.iter().map(rust_struct).collect::<Vec<_>>().join("\n");
    let generated = format!(
        "// Generated by engine/build.rs from shaders/*.wgsl. Do not edit.\n\
         pub static MODULES: &[ModuleSource] = &[\n{modules}];\n\
         pub static KERNELS: &[KernelInfo] = &[\n{table}];\n{consts}\n\
         /// The kernels' push constants, one struct per declaration in `shaders/`, laid out as the\n\
         /// shader lays it out.\n\
         pub mod params {{\n{structs}}}\n\n\
         /// The kernels' storage buffers, named as the shaders name them, in binding order.\n\
         pub mod args {{\nuse crate::tensor::Tensor;\nuse super::{{ArgList, Binds}};\n{args}\n{args_aliases}}}\n"
    );
    std::fs::write(out_dir.join("kernels.rs"), generated).unwrap();
}

/// The module-scope constants the host side takes by name: flags `<FAMILY>_FLAG_<NAME>` (bits
/// of a `Params` field) and op codes `<FAMILY>_OP_<NAME>` (the values of a `Params` field that
/// selects the op); each must be a `u32` literal.
fn flag_constants(module: &naga::Module, shown: &str) -> Result<Vec<(String, u32)>, String> {
    let mut out = Vec::new();
    for (_, c) in module.constants.iter() {
        let Some(name) = c.name.as_ref().filter(|n| n.contains("_FLAG_") || n.contains("_OP_")) else {
            continue;
        };
        match module.global_expressions[c.init] {
            naga::Expression::Literal(naga::Literal::U32(v)) => out.push((name.clone(), v)),
            _ => return Err(format!("{shown}: constant {name} must be a u32 literal")),
        }
    }
    Ok(out)
}

/// Per family, its op codes `<FAMILY>_OP_<NAME>` as `(NAME, code)` in code order: the table a
/// host-side enum is checked against, so that an op added to a shader without a variant (or a
/// variant without its op) fails a test.
fn op_tables(flags: &[(String, u32, String)]) -> String {
    let mut families: std::collections::BTreeMap<&str, Vec<(&str, u32)>> = Default::default();
    for (name, value, _) in flags {
        if let Some((family, op)) = name.split_once("_OP_") {
            families.entry(family).or_default().push((op, *value));
        }
    }
    let mut out = String::new();
    for (family, mut ops) in families {
        ops.sort_by_key(|&(_, v)| v);
        let list: Vec<String> = ops.iter().map(|(n, v)| format!("({n:?}, {v})")).collect();
        writeln!(
            out,
            "/// The op codes `{family}_OP_*` of the shaders, as (name, code).\npub const {family}_OPS: &[(&str, u32)] = &[{}];",
            list.join(", ")
        )
        .unwrap();
    }
    out
}

struct Kernel {
    entry: String,
    workgroup_size: [u32; 3],
    /// (binding, written, the variable's name in the shader, read through a texel buffer), in
    /// binding order.
    bindings: Vec<(u32, bool, String, bool)>,
    push_bytes: u32,
    shared_bytes: u32,
    needs: CapabilityNeeds,
    subgroup_size: Option<u32>,
    /// The Rust name of the push-constant struct's generated mirror (`None`: no push constants).
    params: Option<String>,
}

/// A push-constant struct as the shader lays it out: the file that declares it, its fields
/// (name, Rust type, byte offset, size, the comment beside it in the shader) and its size.
#[derive(Clone, PartialEq)]
struct PushLayout {
    rust_name: String,
    declared_in: String,
    fields: Vec<(String, String, u32, u32, String)>,
    span: u32,
}

/// Replaces each line `// @include NAME` with the text of `shaders/include/NAME`, so that
/// kernels that differ in one declaration (say, the atomic type of an output) share their body.
/// The folder is not compiled on its own.
fn expand_includes(shader_dir: &Path, path: &Path, source: &str) -> Result<String, String> {
    expand_includes_at(shader_dir, path, source, 0)
}

fn expand_includes_at(shader_dir: &Path, path: &Path, source: &str, depth: usize) -> Result<String, String> {
    let mut out = String::with_capacity(source.len());
    for line in source.lines() {
        if let Some(name) = line.strip_prefix("// @include ") {
            let inc = shader_dir.join("include").join(name.trim());
            println!("cargo:rerun-if-changed={}", inc.display());
            let text = std::fs::read_to_string(&inc)
                .map_err(|e| format!("{}: @include {}: {e}", path.display(), inc.display()))?;
            // Included files may include others; a cycle would never end, so depth is bounded.
            if depth >= 4 {
                return Err(format!(
                    "{}: @include {}: nested too deep (a cycle?)",
                    path.display(),
                    name.trim()
                ));
            }
            out.push_str(&expand_includes_at(shader_dir, &inc, &text, depth + 1)?);
        } else {
            out.push_str(line);
        }
        out.push('\n');
    }
    Ok(out)
}

/// Expands a shader into its variants. A file whose first lines read
/// `// @variants NAME: 16 32 64` is compiled once per value (per combination of values, with
/// several such lines), with its line `const NAME: u32 = ...;` set to that value, as module
/// `<stem>_<name><value>...` in the order of the lines (naga's SPIR-V writer has no
/// specialisation constants, so each variant is its own module). Where only some combinations
/// are wanted, one line names several constants and lists the combinations, comma-separated:
/// `// @variants ROWS, COLS: 64 64, 128 128` gives `<stem>_rows64_cols64` and
/// `<stem>_rows128_cols128`.
fn variants(path: &Path, source: &str) -> Result<Vec<(PathBuf, String, String)>, String> {
    let stem = path.file_stem().unwrap().to_str().unwrap().to_string();
    let shown = path.display();
    let mut out = vec![(path.to_path_buf(), stem, source.to_string())];
    for spec in source.lines().map_while(|l| l.strip_prefix("// @variants ")) {
        let (names, values) =
            spec.split_once(':').ok_or_else(|| format!("{shown}: expected `// @variants NAME: v1 v2`"))?;
        let names: Vec<&str> = names.split(',').map(str::trim).collect();
        // The combinations: one value each, or (several names) one comma-separated group each.
        let combinations: Vec<Vec<&str>> = if names.len() == 1 {
            values.split_whitespace().map(|v| vec![v]).collect()
        } else {
            values.split(',').map(|group| group.split_whitespace().collect()).collect()
        };
        // Each constant's declaration line, found once.
        let mut lines = Vec::new();
        for name in &names {
            let decl = format!("const {name}: u32 = ");
            let line = source
                .lines()
                .find(|l| l.starts_with(&decl))
                .ok_or_else(|| format!("{shown}: variants of {name} need a line `{decl}...;`"))?;
            lines.push((decl, line));
        }
        let mut next = Vec::new();
        for combination in &combinations {
            if combination.len() != names.len() {
                return Err(format!(
                    "{shown}: variant `{}` gives {} values for the {} constants {}",
                    combination.join(" "),
                    combination.len(),
                    names.len(),
                    names.join(", ")
                ));
            }
            let values = combination
                .iter()
                .map(|v| v.parse::<u32>().map_err(|_| format!("{shown}: variant value {v:?} is not a u32")))
                .collect::<Result<Vec<u32>, String>>()?;
            for (p, module, text) in &out {
                let (mut module, mut text) = (module.clone(), text.clone());
                for ((name, (decl, line)), value) in names.iter().zip(&lines).zip(&values) {
                    text = text.replacen(line, &format!("{decl}{value}u;"), 1);
                    module = format!("{module}_{}{value}", name.to_lowercase());
                }
                next.push((p.clone(), module, text));
            }
        }
        out = next;
    }
    Ok(out)
}

/// A SPIR-V module, its kernels, and its flag constants (module-scope `const NAME_FLAG_X: u32`,
/// a bit of a `Params` field that the host side takes by name).
type Compiled = (Vec<u32>, Vec<Kernel>, Vec<(String, u32)>, Option<PushLayout>);

fn compile(shader_dir: &Path, path: &Path, source: &str) -> Result<Compiled, String> {
    let shown = path.display().to_string();
    let module =
        naga::front::wgsl::parse_str(source).map_err(|e| e.emit_to_string_with_path(source, &shown))?;
    let mut validator = naga::valid::Validator::new(ValidationFlags::all(), Capabilities::all());
    validator.subgroup_stages(ShaderStages::COMPUTE).subgroup_operations(SubgroupOperationSet::all());
    let info = validator.validate(&module).map_err(|e| e.emit_to_string_with_path(source, &shown))?;
    let flags = flag_constants(&module, &shown)?;

    // No array crosses a function boundary: with the layout decorations removed from arrays in
    // function memory (see `strip_layouts_outside_buffers`), lavapipe (Mesa 25) read stale memory
    // for an array passed by value: the raster backward's subgroup sums, so that two processes
    // and one process accumulating two micro-batches trained apart (tools/tests/
    // distributed_train.rs). Arrays stay in their function; a struct or scalars cross instead.
    for (_, f) in module.functions.iter() {
        let by_value = f.arguments.iter().map(|a| a.ty).chain(f.result.as_ref().map(|r| r.ty));
        for ty in by_value {
            if matches!(module.types[ty].inner, naga::TypeInner::Array { .. }) {
                return Err(format!(
                    "{shown}: function {} takes or returns an array by value; pass its elements, a \
                     struct or a pointer instead (engine/build.rs says why)",
                    f.name.as_deref().unwrap_or("?")
                ));
            }
        }
    }

    let options = spv::Options {
        lang_version: (1, 5),
        // A bounded-loop guard on every loop cost a tiled matmul 10x on an H100
        // (docs/decisions/foundations.md).
        force_loop_bounding: false,
        // Kernels check their own bounds.
        bounds_check_policies: naga::proc::BoundsCheckPolicies {
            index: naga::proc::BoundsCheckPolicy::Unchecked,
            buffer: naga::proc::BoundsCheckPolicy::Unchecked,
            image_load: naga::proc::BoundsCheckPolicy::Unchecked,
            binding_array: naga::proc::BoundsCheckPolicy::Unchecked,
        },
        zero_initialize_workgroup_memory: spv::ZeroInitializeWorkgroupMemoryMode::None,
        emit_int_div_checks: false,
        ..Default::default()
    };
    let words = spv::write_vec(&module, &info, &options, None)
        .map_err(|e| format!("{shown}: SPIR-V generation failed: {e}"))?;
    let words = flatten_access_chains(&words);
    let words = bitcast_unpacked_halves(&words);
    let words = strip_layouts_outside_buffers(&words).map_err(|e| format!("{shown}: {e}"))?;
    let words = strip_capabilities(&words, UNUSED_CAPABILITIES);
    let words = texel_buffers(&words);
    // What the module needs of the device, from the capabilities it declares.
    let needs = capability_needs(&words).map_err(|e| format!("{shown}: {e}"))?;
    // `// @subgroup_size N`: the kernels of the file are written for subgroups of exactly N.
    let mut subgroup_size = None;
    for line in source.lines() {
        if let Some(v) = line.strip_prefix("// @subgroup_size ") {
            let n: u32 =
                v.trim().parse().map_err(|_| format!("{shown}: `// @subgroup_size {v}` is not a number"))?;
            if !n.is_power_of_two() {
                return Err(format!("{shown}: @subgroup_size {n} is not a power of two"));
            }
            subgroup_size = Some(n);
        }
    }

    let layout = push_layout(shader_dir, path, &module)?;
    let mut kernels = Vec::new();
    for (i, ep) in module.entry_points.iter().enumerate() {
        if ep.stage != naga::ShaderStage::Compute {
            continue;
        }
        let ep_info = info.get_entry_point(i);
        let mut bindings = Vec::new();
        let mut push_bytes = 0u32;
        let mut shared_bytes = 0u32;
        for (handle, var) in module.global_variables.iter() {
            let usage = ep_info[handle];
            match var.space {
                naga::AddressSpace::WorkGroup if !usage.is_empty() => {
                    shared_bytes += module.types[var.ty].inner.size(module.to_ctx());
                }
                naga::AddressSpace::Storage { access } => {
                    let b = var
                        .binding
                        .as_ref()
                        .ok_or_else(|| format!("{shown}: storage variable without @group/@binding"))?;
                    if b.group != 0 {
                        return Err(format!("{shown}: kernels use @group(0) only"));
                    }
                    // A binding the entry point never touches is still bound (the layout is
                    // per entry point, positional), but it is neither read nor written. One it
                    // touches counts as written where this entry point writes it or where the
                    // module declares it `read_write`: SPIR-V marks the variable, not each entry
                    // point's use, so the validation layer takes a read_write binding that an
                    // entry point only reads (a norm's statistics, read by its backward passes)
                    // as written, and its synchronization checks want the barriers for that.
                    if !usage.is_empty() {
                        let declared = access.contains(naga::StorageAccess::STORE);
                        let name = var
                            .name
                            .clone()
                            .ok_or_else(|| format!("{shown}: binding {} has no name", b.binding))?;
                        bindings.push((b.binding, usage.contains(GlobalUse::WRITE) || declared, name, false));
                    }
                }
                naga::AddressSpace::Handle if is_texel_buffer(&module.types[var.ty].inner) => {
                    let b = var
                        .binding
                        .as_ref()
                        .ok_or_else(|| format!("{shown}: texel buffer without @group/@binding"))?;
                    if b.group != 0 {
                        return Err(format!("{shown}: kernels use @group(0) only"));
                    }
                    if !usage.is_empty() {
                        let name = var
                            .name
                            .clone()
                            .ok_or_else(|| format!("{shown}: binding {} has no name", b.binding))?;
                        bindings.push((b.binding, false, name, true));
                    }
                }
                naga::AddressSpace::Immediate if !usage.is_empty() => {
                    push_bytes = module.types[var.ty].inner.size(module.to_ctx());
                }
                naga::AddressSpace::Uniform | naga::AddressSpace::Handle => {
                    return Err(format!(
                        "{shown}: kernels take storage buffers, texel buffers \
                         (`texture_storage_1d<rgba32float, read>`) and immediates (push constants) only"
                    ));
                }
                _ => {}
            }
        }
        bindings.sort();
        kernels.push(Kernel {
            entry: ep.name.clone(),
            workgroup_size: ep.workgroup_size,
            bindings,
            push_bytes,
            shared_bytes,
            needs,
            subgroup_size,
            params: (push_bytes > 0).then(|| layout.as_ref().map(|l| l.rust_name.clone())).flatten(),
        });
    }
    if kernels.iter().any(|k| k.push_bytes > 0 && k.params.is_none()) {
        return Err(format!("{shown}: push constants must be a struct"));
    }
    Ok((words, kernels, flags, layout))
}

/// The layout of the module's push-constant struct (`var<immediate> pc: Params;`), named after
/// the file that declares the struct (a shader or an include), so that kernels sharing a
/// declaration share one Rust type.
fn push_layout(shader_dir: &Path, path: &Path, module: &naga::Module) -> Result<Option<PushLayout>, String> {
    let shown = path.display().to_string();
    let mut found = None;
    for (_, var) in module.global_variables.iter() {
        if var.space != naga::AddressSpace::Immediate {
            continue;
        }
        if found.is_some() {
            return Err(format!("{shown}: one `var<immediate>` per module"));
        }
        let ty = &module.types[var.ty];
        let (naga::TypeInner::Struct { members, span }, Some(name)) = (&ty.inner, ty.name.as_ref()) else {
            return Err(format!("{shown}: `var<immediate>` must have a named struct type"));
        };
        let (file, text) = declaring_file(shader_dir, path, name, 0)?
            .ok_or_else(|| format!("{shown}: cannot find `struct {name} {{` in the file or its includes"))?;
        let stem = Path::new(&file).file_stem().unwrap().to_str().unwrap().to_string();
        let mut rust_name = camel(&stem);
        if !rust_name.ends_with("Params") {
            rust_name.push_str("Params");
        }
        let comments = field_comments(&text, name);
        let mut fields = Vec::new();
        for m in members {
            let field =
                m.name.clone().ok_or_else(|| format!("{shown}: struct {name} has an unnamed member"))?;
            let inner = &module.types[m.ty].inner;
            let scalar = |s: &naga::Scalar| match (s.kind, s.width) {
                (naga::ScalarKind::Uint, 4) => Ok("u32"),
                (naga::ScalarKind::Sint, 4) => Ok("i32"),
                (naga::ScalarKind::Float, 4) => Ok("f32"),
                _ => Err(format!("{shown}: {name}.{field}: push constants hold 32-bit scalars")),
            };
            let rust = match inner {
                naga::TypeInner::Scalar(s) => scalar(s)?.to_string(),
                naga::TypeInner::Vector { size, scalar: s } => format!("[{}; {}]", scalar(s)?, *size as u32),
                naga::TypeInner::Array { base, size: naga::ArraySize::Constant(n), stride: 4 } => {
                    match &module.types[*base].inner {
                        naga::TypeInner::Scalar(s) => format!("[{}; {n}]", scalar(s)?),
                        _ => return Err(format!("{shown}: {name}.{field}: arrays of scalars only")),
                    }
                }
                _ => {
                    return Err(format!(
                        "{shown}: {name}.{field}: scalars, vectors and arrays of scalars only"
                    ))
                }
            };
            let size = inner.size(module.to_ctx());
            let comment =
                comments.iter().find(|(f, _)| *f == field).map(|(_, c)| c.clone()).unwrap_or_default();
            fields.push((field, rust, m.offset, size, comment));
        }
        found = Some(PushLayout { rust_name, declared_in: file, fields, span: *span });
    }
    Ok(found)
}

/// The file (the shader or one it includes, depth first) that declares `struct NAME {`, and its
/// text.
fn declaring_file(
    shader_dir: &Path,
    path: &Path,
    name: &str,
    depth: usize,
) -> Result<Option<(String, String)>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let decl = format!("struct {name} {{");
    if text.lines().any(|l| l.trim_start().starts_with(&decl)) {
        let rel = path.strip_prefix(shader_dir.parent().unwrap()).unwrap_or(path);
        return Ok(Some((rel.display().to_string(), text)));
    }
    if depth < 4 {
        for inc in text.lines().filter_map(|l| l.strip_prefix("// @include ")) {
            if let Some(found) =
                declaring_file(shader_dir, &shader_dir.join("include").join(inc.trim()), name, depth + 1)?
            {
                return Ok(Some(found));
            }
        }
    }
    Ok(None)
}

/// Each field's comment in the declaration of `struct NAME`: the `//` lines just above it and
/// the one at the end of its line.
fn field_comments(text: &str, name: &str) -> Vec<(String, String)> {
    let decl = format!("struct {name} {{");
    let mut out = Vec::new();
    let mut above: Vec<String> = Vec::new();
    let mut inside = false;
    for line in text.lines() {
        let t = line.trim();
        if !inside {
            inside = t.starts_with(&decl);
            continue;
        }
        if t.starts_with('}') {
            break;
        }
        if let Some(c) = t.strip_prefix("//") {
            above.push(c.trim().to_string());
            continue;
        }
        let (code, trailing) = match t.split_once("//") {
            Some((c, r)) => (c, Some(r.trim().to_string())),
            None => (t, None),
        };
        if let Some((field, _)) = code.split_once(':') {
            let mut parts = std::mem::take(&mut above);
            parts.extend(trailing);
            out.push((field.trim().to_string(), parts.join(" ")));
        }
    }
    out
}

/// `snake_case` to `CamelCase`.
fn camel(s: &str) -> String {
    s.split('_').filter(|w| !w.is_empty()).map(|w| w[..1].to_uppercase() + &w[1..].to_lowercase()).collect()
}

/// A kernel's argument struct: a tensor per storage binding the entry point uses, in binding
/// order, and its [`Binds`] and [`ArgList`] implementations.
fn args_struct(name: &str, fields: &[String], from: &str) -> String {
    let mut out = format!("/// The buffers of `{from}` (generated from the shader).\n#[derive(Clone, Copy)]\npub struct {name}<'a> {{\n");
    for f in fields {
        writeln!(out, "    pub {f}: &'a Tensor,").unwrap();
    }
    out.push_str("}\n");
    let list = fields.iter().map(|f| format!("self.{f}")).collect::<Vec<_>>().join(", ");
    writeln!(
        out,
        "impl Binds for {name}<'static> {{\n    type Args<'a> = {name}<'a>;\n}}\n\
         impl<'a> ArgList<'a> for {name}<'a> {{\n    type List = [&'a Tensor; {}];\n    fn tensors(&self) -> Self::List {{\n        [{list}]\n    }}\n}}",
        fields.len()
    )
    .unwrap();
    out
}

/// The Rust mirror of a push-constant struct: the shader's fields at the shader's offsets, with
/// explicit padding where WGSL's alignment leaves a gap.
fn rust_struct(l: &PushLayout) -> String {
    let mut out = format!(
        "/// The push constants of `{}` (generated from the shader's declaration).\n\
         #[repr(C)]\n\
         #[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]\n\
         pub struct {} {{\n",
        l.declared_in, l.rust_name
    );
    let mut at = 0;
    let mut pads = 0;
    let mut pad = |out: &mut String, at: &mut u32, to: u32| {
        if to > *at {
            writeln!(out, "    pub _pad{pads}: [u32; {}],", (to - *at) / 4).unwrap();
            pads += 1;
            *at = to;
        }
    };
    for (name, ty, offset, size, comment) in &l.fields {
        pad(&mut out, &mut at, *offset);
        if !comment.is_empty() {
            writeln!(out, "    /// {comment}").unwrap();
        }
        writeln!(out, "    pub {name}: {ty},").unwrap();
        at = offset + size;
    }
    pad(&mut out, &mut at, l.span);
    out.push_str(
        "}
",
    );
    out
}

/// The instructions of a SPIR-V module after its 5-word header: each one's offset in `words`
/// and its words (the opcode in the low half of the first, the word count in the high half).
fn instructions(words: &[u32]) -> impl Iterator<Item = (usize, &[u32])> {
    let mut at = 5;
    std::iter::from_fn(move || {
        let count = ((*words.get(at)? >> 16) as usize).max(1);
        let inst = &words[at..(at + count).min(words.len())];
        at += count;
        Some((at - count, inst))
    })
}

/// Rewrites every access chain whose base is another access chain as one chain from the root,
/// its indices the base's followed by its own. naga hoists `&buffer.data` into a chain at the top
/// of a function and indexes that chain later; the Khronos validation layer (1.3.239, Debian 12's)
/// follows a store's pointer back one chain only, so it took every storage buffer the kernels
/// write for one they only read, and its synchronization checks missed every hazard on a write.
/// One chain means the same address; drivers fold chains anyway.
fn flatten_access_chains(words: &[u32]) -> Vec<u32> {
    const ACCESS_CHAIN: u32 = 65;
    const IN_BOUNDS_ACCESS_CHAIN: u32 = 66;
    let mut out = words[..5].to_vec();
    // Result id of a chain -> (root base, all indices, in bounds).
    let mut chains: std::collections::HashMap<u32, (u32, Vec<u32>, bool)> = Default::default();
    for (_, inst) in instructions(words) {
        let (count, opcode) = (inst.len(), inst[0] & 0xffff);
        if (opcode == ACCESS_CHAIN || opcode == IN_BOUNDS_ACCESS_CHAIN) && count >= 4 {
            let (ty, id, base) = (inst[1], inst[2], inst[3]);
            let own = &inst[4..];
            let in_bounds = opcode == IN_BOUNDS_ACCESS_CHAIN;
            let (root, mut indices, base_in_bounds) = match chains.get(&base) {
                Some((root, indices, b)) => (*root, indices.clone(), *b),
                None => (base, Vec::new(), true),
            };
            indices.extend_from_slice(own);
            let in_bounds = in_bounds && base_in_bounds;
            let op = if in_bounds { IN_BOUNDS_ACCESS_CHAIN } else { ACCESS_CHAIN };
            out.push(((4 + indices.len() as u32) << 16) | op);
            out.extend_from_slice(&[ty, id, root]);
            out.extend_from_slice(&indices);
            chains.insert(id, (root, indices, in_bounds));
        } else {
            out.extend_from_slice(inst);
        }
    }
    out
}

/// Turns `vec2<f16>(unpack2x16float(w))` into a bitcast of `w`. WGSL (naga 30) has no
/// size-changing bitcast, so the kernels that stage packed f16 words as halves (the
/// cooperative matmul's `put`, the cooperative attention's `unpack4`) write the round trip
/// through f32: UnpackHalf2x16, then FConvert to a vector of two 16-bit floats. Each such
/// FConvert of an UnpackHalf2x16 becomes an OpBitcast of the packed word (the same length, so
/// in place; the unpack is left dead for the driver to drop): the same bits for every half,
/// NaN payloads included, and no conversion instructions. Every other conversion is untouched.
fn bitcast_unpacked_halves(words: &[u32]) -> Vec<u32> {
    const OP_EXT_INST_IMPORT: u32 = 11;
    const OP_EXT_INST: u32 = 12;
    const OP_TYPE_FLOAT: u32 = 22;
    const OP_TYPE_VECTOR: u32 = 23;
    const OP_FCONVERT: u32 = 115;
    const OP_BITCAST: u32 = 124;
    const UNPACK_HALF_2X16: u32 = 62;
    let mut glsl = None;
    let mut half = None;
    let mut half2 = Vec::new();
    let mut unpacked: std::collections::HashMap<u32, u32> = Default::default(); // result -> word
    for (_, inst) in instructions(words) {
        let count = inst.len();
        match inst[0] & 0xffff {
            OP_EXT_INST_IMPORT if count >= 3 => {
                let name: Vec<u8> =
                    inst[2..].iter().flat_map(|w| w.to_le_bytes()).take_while(|&b| b != 0).collect();
                if name == b"GLSL.std.450" {
                    glsl = Some(inst[1]);
                }
            }
            OP_TYPE_FLOAT if count >= 3 && inst[2] == 16 => half = Some(inst[1]),
            OP_TYPE_VECTOR if count == 4 && Some(inst[2]) == half && inst[3] == 2 => half2.push(inst[1]),
            OP_EXT_INST if count == 6 && Some(inst[3]) == glsl && inst[4] == UNPACK_HALF_2X16 => {
                unpacked.insert(inst[2], inst[5]);
            }
            _ => {}
        }
    }
    let mut out = words.to_vec();
    for (at, inst) in instructions(words) {
        if inst[0] & 0xffff == OP_FCONVERT && inst.len() == 4 && half2.contains(&inst[1]) {
            if let Some(&word) = unpacked.get(&inst[3]) {
                out[at] = (4 << 16) | OP_BITCAST;
                out[at + 3] = word;
            }
        }
    }
    out
}

/// Removes the explicit layout decorations (ArrayStride, Offset, MatrixStride) from types that
/// only workgroup, function or private variables use. naga decorates every array and struct;
/// Vulkan allows explicit layouts only on types of buffers and push constants, and spirv-val as
/// newer validation layers run it rejects the rest (VUID-StandaloneSpirv-None-10684: seen on
/// FPS's workgroup arrays and the kernels' local arrays). A type used by both kinds would need
/// two copies; no kernel has one, and the build stops if one appears.
fn strip_layouts_outside_buffers(words: &[u32]) -> Result<Vec<u32>, String> {
    const OP_DECORATE: u32 = 71;
    const OP_MEMBER_DECORATE: u32 = 72;
    const OP_TYPE_ARRAY: u32 = 28;
    const OP_TYPE_RUNTIME_ARRAY: u32 = 29;
    const OP_TYPE_STRUCT: u32 = 30;
    const OP_TYPE_POINTER: u32 = 32;
    const OP_TYPE_MATRIX: u32 = 24;
    const ARRAY_STRIDE: u32 = 6;
    const MATRIX_STRIDE: u32 = 7;
    const OFFSET: u32 = 35;
    // Storage classes with explicit layouts: Uniform, PushConstant, StorageBuffer,
    // PhysicalStorageBuffer (UniformConstant holds no data of these types).
    const EXPLICIT: [u32; 4] = [2, 9, 12, 5349];
    let mut children: std::collections::HashMap<u32, Vec<u32>> = Default::default();
    let mut pointers = Vec::new(); // (storage class, pointee)
    for (_, inst) in instructions(words) {
        let count = inst.len();
        match inst[0] & 0xffff {
            OP_TYPE_ARRAY | OP_TYPE_RUNTIME_ARRAY | OP_TYPE_MATRIX if count >= 3 => {
                children.insert(inst[1], vec![inst[2]]);
            }
            OP_TYPE_STRUCT => {
                children.insert(inst[1], inst[2..].to_vec());
            }
            OP_TYPE_POINTER if count == 4 => pointers.push((inst[2], inst[3])),
            _ => {}
        }
    }
    let reach = |roots: &mut dyn Iterator<Item = u32>| {
        let mut seen = std::collections::HashSet::new();
        let mut stack: Vec<u32> = roots.collect();
        while let Some(t) = stack.pop() {
            if seen.insert(t) {
                stack.extend(children.get(&t).into_iter().flatten());
            }
        }
        seen
    };
    let laid_out = reach(&mut pointers.iter().filter(|(c, _)| EXPLICIT.contains(c)).map(|&(_, t)| t));
    let plain = reach(&mut pointers.iter().filter(|(c, _)| !EXPLICIT.contains(c)).map(|&(_, t)| t));
    let strip: std::collections::HashSet<u32> = plain.difference(&laid_out).copied().collect();
    let mut out = words[..5].to_vec();
    for (_, inst) in instructions(words) {
        let count = inst.len();
        let layout = match inst[0] & 0xffff {
            OP_DECORATE if count >= 3 => {
                [ARRAY_STRIDE, MATRIX_STRIDE, OFFSET].contains(&inst[2]).then_some(inst[1])
            }
            OP_MEMBER_DECORATE if count >= 4 => [MATRIX_STRIDE, OFFSET].contains(&inst[3]).then_some(inst[1]),
            _ => None,
        };
        match layout {
            Some(t) if strip.contains(&t) => {}
            Some(t) if plain.contains(&t) && children.contains_key(&t) => {
                return Err(format!(
                    "SPIR-V type %{t} is used both in a buffer and in workgroup or function memory; \
                     explicit layouts cannot be removed from it (give the variable a type of its own)"
                ));
            }
            _ => out.extend_from_slice(inst),
        }
    }
    Ok(out)
}

const OP_CAPABILITY: u32 = 17;

/// Whether a global of this type is a texel buffer (see the module doc): a read-only 1D storage
/// image of `rgba32float`.
fn is_texel_buffer(ty: &naga::TypeInner) -> bool {
    matches!(
        ty,
        naga::TypeInner::Image {
            dim: naga::ImageDimension::D1,
            arrayed: false,
            class: naga::ImageClass::Storage { format: naga::StorageFormat::Rgba32Float, access },
        } if *access == naga::StorageAccess::LOAD
    )
}

/// Makes every 1D image of the module a buffer image: `OpTypeImage`'s `Dim 1D` becomes `Dim
/// Buffer` and the capability `Image1D` becomes `ImageBuffer` (`compile` admits no other 1D
/// image). Reads keep their form: `OpImageRead` takes one integer coordinate for both.
fn texel_buffers(words: &[u32]) -> Vec<u32> {
    const OP_TYPE_IMAGE: u32 = 25;
    const DIM_1D: u32 = 0;
    const DIM_BUFFER: u32 = 5;
    const IMAGE_1D: u32 = 44;
    const IMAGE_BUFFER: u32 = 47;
    let mut out = words.to_vec();
    for (at, inst) in instructions(words) {
        match inst[0] & 0xffff {
            OP_TYPE_IMAGE if inst.len() >= 9 && inst[3] == DIM_1D => out[at + 3] = DIM_BUFFER,
            OP_CAPABILITY if inst.len() == 2 && inst[1] == IMAGE_1D => out[at + 1] = IMAGE_BUFFER,
            _ => {}
        }
    }
    out
}

/// Capabilities naga declares for every `enable f16` module that compute kernels never use:
/// f16 in uniform buffers (the kernels take none: `compile` refuses them) and f16 shader inputs
/// and outputs (a compute shader's only inputs are its u32 builtins). The engine enables neither
/// feature (NVIDIA reports `storageInputOutput16 = false`), and a module that declares a
/// capability the device was not created with is invalid (VUID-VkShaderModuleCreateInfo-pCode-08740).
const UNUSED_CAPABILITIES: &[u32] = &[
    4434, // UniformAndStorageBuffer16BitAccess
    4436, // StorageInputOutput16
];

/// The module without the `OpCapability` instructions of `drop`.
fn strip_capabilities(words: &[u32], drop: &[u32]) -> Vec<u32> {
    let mut out = words[..5].to_vec();
    for (_, inst) in instructions(words) {
        if !(inst[0] & 0xffff == OP_CAPABILITY && inst.len() == 2 && drop.contains(&inst[1])) {
            out.extend_from_slice(inst);
        }
    }
    out
}

/// What a module needs of the device, read from the capabilities it declares: each one the
/// engine knows maps to the feature it enables at device creation (engine/src/device.rs), and one
/// it does not know stops the build, so that no module can ask for a feature the device was not
/// created with.
#[derive(Clone, Copy, Default)]
struct CapabilityNeeds {
    f16: bool,
    float_atomics: bool,
    coop_matrix: bool,
    memory_model: bool,
    /// `VkSubgroupFeatureFlags` bits: BASIC 1, VOTE 2, ARITHMETIC 4, BALLOT 8, SHUFFLE 16.
    subgroup_ops: u32,
}

fn capability_needs(words: &[u32]) -> Result<CapabilityNeeds, String> {
    let mut needs = CapabilityNeeds::default();
    for (_, inst) in instructions(words) {
        if inst[0] & 0xffff == OP_CAPABILITY && inst.len() == 2 {
            match inst[1] {
                1 => {}  // Shader
                47 => {} // ImageBuffer (texel buffers; every Vulkan device has it)
                // Float16 (shaderFloat16) and StorageBuffer16BitAccess (storageBuffer16BitAccess):
                // the engine enables both together, or neither.
                9 | 4433 => needs.f16 = true,
                6033 => needs.float_atomics = true, // AtomicFloat32AddEXT
                6022 => needs.coop_matrix = true,   // CooperativeMatrixKHR
                5345 => needs.memory_model = true,  // VulkanMemoryModel
                61 => needs.subgroup_ops |= 1,      // GroupNonUniform
                62 => needs.subgroup_ops |= 1 | 2,  // ...Vote
                63 => needs.subgroup_ops |= 1 | 4,  // ...Arithmetic
                64 => needs.subgroup_ops |= 1 | 8,  // ...Ballot
                65 => needs.subgroup_ops |= 1 | 16, // ...Shuffle
                other => {
                    return Err(format!(
                        "the SPIR-V declares capability {other}, which the engine neither enables nor \
                         checks for (engine/build.rs, capability_needs)"
                    ))
                }
            }
        }
    }
    Ok(needs)
}

fn bytemuck_words(words: &[u32]) -> Vec<u8> {
    words.iter().flat_map(|w| w.to_le_bytes()).collect()
}
