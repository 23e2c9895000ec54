#include "libmodel/format/model.h"

#include "libmodel/format/atomic.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <iomanip>
#include <map>
#include <sstream>

namespace fs = std::filesystem;

namespace orthosim {

std::string voxel_geometry_problem(const std::array<double, 3>& spacing_m, const std::array<double, 3>& origin_m) {
  auto num = [](double x) {  // enough digits that a value out of range does not print as the bound
    std::ostringstream o;
    o << std::setprecision(10) << x;
    return o.str();
  };
  for (int k = 0; k < 3; ++k) {
    const double s = spacing_m[static_cast<std::size_t>(k)], o = origin_m[static_cast<std::size_t>(k)];
    if (!(s >= kMinVoxelSpacingM && s <= kMaxVoxelSpacingM))
      return std::string("spacing along ") + "xyz"[k] + " is " + num(s) + " m: each voxel size must be in [" +
             num(kMinVoxelSpacingM) + ", " + num(kMaxVoxelSpacingM) + "] m";
    if (!(std::abs(o) <= kMaxOriginM))
      return std::string("origin along ") + "xyz"[k] + " is " + num(o) + " m: it must be finite, within +-" +
             num(kMaxOriginM) + " m";
  }
  return "";
}

std::string format_version() {
  return std::to_string(kFormatMajor) + "." + std::to_string(kFormatMinor);
}

int Volume::label_of(const std::string& name) const {
  for (std::size_t i = 0; i < label_names.size(); ++i)
    if (label_names[i] == name) return static_cast<int>(i);
  return -1;
}

namespace {

template <class M> constexpr int width_of() { return M::ColsAtCompileTime; }

// writes each visited field as a dataset under `group`
struct FieldWriter {
  h5::File& f;
  std::string group;
  template <class M>
  void operator()(const M& m, const char* name, const char*, const char* unit, const char* doc) {
    using T = typename M::Scalar;
    std::vector<std::uint64_t> dims{static_cast<std::uint64_t>(m.rows())};
    if (width_of<M>() != 1) dims.push_back(static_cast<std::uint64_t>(width_of<M>()));
    f.write<T>(group + "/" + name, m.data(), dims, unit, doc);
  }
};

// reads each visited field (or only those named in `only`)
struct FieldReader {
  const h5::File& f;
  std::string group;
  const std::vector<std::string>* only = nullptr;
  template <class M>
  void operator()(M& m, const char* name, const char*, const char*, const char*) {
    if (only && std::find(only->begin(), only->end(), name) == only->end()) return;
    using T = typename M::Scalar;
    const std::string path = group + "/" + name;
    if (!f.exists(path)) throw Error(f.path(), "missing dataset " + path);
    std::vector<std::uint64_t> dims = f.dims(path);
    constexpr int w = width_of<M>();
    const bool ok = (w == 1 && dims.size() == 1) || (w != 1 && dims.size() == 2 && dims[1] == static_cast<std::uint64_t>(w));
    if (!ok) {
      std::ostringstream s;
      s << path << " has shape (";
      for (std::size_t i = 0; i < dims.size(); ++i) s << (i ? " x " : "") << dims[i];
      s << "), expected (n" << (w == 1 ? "" : " x " + std::to_string(w)) << ")";
      throw Error(f.path(), s.str());
    }
    std::vector<T> data = f.read<T>(path, nullptr);
    m.resize(static_cast<Eigen::Index>(dims[0]), w);
    if (!data.empty()) std::memcpy(m.data(), data.data(), data.size() * sizeof(T));
  }
};

struct CountChecker {
  std::string file, group;
  const std::vector<std::string>* only = nullptr;
  std::map<std::string, std::pair<Eigen::Index, std::string>> seen;
  template <class M>
  void operator()(const M& m, const char* name, const char* count, const char*, const char*) {
    if (only && std::find(only->begin(), only->end(), name) == only->end()) return;
    auto it = seen.find(count);
    if (it == seen.end()) {
      seen[count] = {m.rows(), name};
    } else if (it->second.first != m.rows()) {
      throw Error(file, group + ": " + name + " has " + std::to_string(m.rows()) + " rows but " +
                            it->second.second + " has " + std::to_string(it->second.first) +
                            " (both count " + count + ")");
    }
  }
};

template <class S>
void write_group(h5::File& f, const std::string& group, const S& s) {
  S& m = const_cast<S&>(s);  // fields() only hands out references; nothing is modified
  check_counts(m, f.path(), group);
  f.remove(group);
  f.make_groups(group);
  m.fields(FieldWriter{f, group});
}

template <class S>
S read_group(const h5::File& f, const std::string& group, const std::vector<std::string>* only = nullptr) {
  if (!f.is_group(group)) throw Error(f.path(), "missing group " + group);
  S s;
  s.fields(FieldReader{f, group, only});
  CountChecker c{f.path(), group, only, {}};
  s.fields(c);
  return s;
}

std::string read_str_attr_or(const h5::File& f, const std::string& obj, const std::string& name,
                             const std::string& fallback) {
  return f.has_attr(obj, name) ? f.attr_string(obj, name) : fallback;
}

}  // namespace

template <class S>
void check_counts(S& s, const std::string& file, const std::string& group) {
  CountChecker c{file, group, nullptr, {}};
  s.fields(c);
}
template void check_counts(Surface&, const std::string&, const std::string&);
template void check_counts(QuadSurface&, const std::string&, const std::string&);
template void check_counts(Layer&, const std::string&, const std::string&);
template void check_counts(VesselTree&, const std::string&, const std::string&);
template void check_counts(Tuning&, const std::string&, const std::string&);

void check_index_range(
    const Eigen::Ref<const Eigen::Matrix<std::int32_t, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>>& ids,
    std::int64_t n, const std::string& file, const std::string& what) {
  if (ids.size() == 0) return;
  std::int64_t lo = ids.minCoeff(), hi = ids.maxCoeff();
  if (lo < 0 || hi >= n)
    throw Error(file, what + " has index " + std::to_string(lo < 0 ? lo : hi) + " outside [0, " +
                          std::to_string(n) + ")");
}

// ---- reader ----------------------------------------------------------------

ModelReader::ModelReader(const std::string& path) : file_(path, h5::File::Mode::read) {
  if (!file_.has_attr("/", "orthosim_format"))
    throw Error(path, "not an orthosim model file (no orthosim_format attribute on /)");
  std::string v = file_.attr_string("/", "orthosim_format");
  int major = 0;
  try {
    major = std::stoi(v.substr(0, v.find('.')));
  } catch (...) {
    throw Error(path, "unreadable orthosim_format '" + v + "'");
  }
  if (major > kFormatMajor)
    throw Error(path, "format " + v + " is newer than this build reads (" + format_version() +
                          "); upgrade orthosim");
  if (major < 1) throw Error(path, "unsupported orthosim_format '" + v + "'");
}

std::string ModelReader::version() const { return file_.attr_string("/", "orthosim_format"); }

Volume ModelReader::volume() const {
  const std::string g = "/volume";
  if (!file_.is_group(g)) throw Error(path(), "missing group /volume");
  Volume v;
  std::vector<std::uint64_t> dims;
  if (!file_.exists(g + "/labels")) throw Error(path(), "missing dataset /volume/labels");
  if (file_.dims(g + "/labels").size() != 3)
    throw Error(path(), "/volume/labels must be 3-D [nz][ny][nx]");
  v.labels = file_.read<std::uint8_t>(g + "/labels", &dims);
  v.nz = static_cast<int>(dims[0]);
  v.ny = static_cast<int>(dims[1]);
  v.nx = static_cast<int>(dims[2]);
  auto sp = file_.attr_doubles(g, "spacing_m");
  auto org = file_.attr_doubles(g, "origin_m");
  if (sp.size() != 3 || org.size() != 3) throw Error(path(), "/volume spacing_m and origin_m need 3 values");
  for (int i = 0; i < 3; ++i) {
    v.spacing_m[i] = sp[i];
    v.origin_m[i] = org[i];
  }
  if (const std::string why = voxel_geometry_problem(v.spacing_m, v.origin_m); !why.empty())
    throw Error(path(), "/volume: " + why);
  v.label_names = file_.attr_strings(g, "label_names");
  // every label with voxels needs a name: surface crashed (a label past the
  // names, SIGSEGV after its output was committed) or left the label out
  // silently (an empty name) (sweep of 2026-11-27)
  std::array<bool, 256> present{};
  for (std::uint8_t l : v.labels) present[l] = true;
  for (std::size_t l = 1; l < present.size(); ++l) {
    if (!present[l]) continue;
    if (l >= v.label_names.size())
      throw Error(path(), "/volume/labels holds label " + std::to_string(l) + " but label_names has " +
                              std::to_string(v.label_names.size()) + " entries");
    if (v.label_names[l].empty())
      throw Error(path(), "/volume/labels holds label " + std::to_string(l) + ", which label_names leaves unnamed");
  }
  return v;
}

Surface ModelReader::surface(const std::string& tissue) const {
  auto s = read_group<Surface>(file_, "/surfaces/" + tissue);
  check_index_range(s.faces, s.vertices.rows(), path(), "/surfaces/" + tissue + "/faces");
  return s;
}

QuadSurface ModelReader::quads(const std::string& tissue) const {
  const std::string g = "/quads/" + tissue;
  auto q = read_group<QuadSurface>(file_, g);
  q.nu = static_cast<int>(file_.attr_int(g, "nu"));
  q.nv = static_cast<int>(file_.attr_int(g, "nv"));
  if (static_cast<Eigen::Index>(q.nu) * q.nv != q.vertices.rows())
    throw Error(path(), g + ": nu*nv does not match the vertex count");
  check_index_range(q.quads, q.vertices.rows(), path(), g + "/quads");
  // texture coordinates (remesh: the grid's arc and axis fractions): remesh's
  // viewer exports (OBJ, glTF) carry them as they are
  for (Eigen::Index i = 0; i < q.uv.rows(); ++i)
    for (Eigen::Index k = 0; k < q.uv.cols(); ++k)
      if (!(q.uv(i, k) >= 0 && q.uv(i, k) <= 1))
        throw Error(path(), g + "/uv: vertex " + std::to_string(i) + " has a texture coordinate outside [0, 1] (" +
                                std::to_string(q.uv(i, k)) + ")");
  return q;
}

namespace {
void read_layer_attrs(const h5::File& f, const std::string& g, Layer& l) {
  l.tissue = f.attr_string(g, "tissue");
  l.kind = f.attr_string(g, "kind");
  if (l.kind != "tetra" && l.kind != "lattice" && l.kind != "rigid")
    throw Error(f.path(), g + ": attribute kind must be tetra, lattice or rigid, not '" + l.kind + "'");
  const std::int64_t order = f.attr_int(g, "order");
  if (order < 0 || order > 1000000) throw Error(f.path(), g + ": attribute order must be in 0..1000000, not " + std::to_string(order));
  l.order = static_cast<int>(order);
  l.node_offset = f.attr_int(g, "node_offset");
  if (f.has_attr(g, "spring_law")) {
    l.spring_law = f.attr_doubles(g, "spring_law");
    if (l.spring_law.size() != 12) throw Error(f.path(), g + ": attribute spring_law must hold 12 values (3 for each of 4 spring classes)");
    for (std::size_t k = 0; k < 12; ++k) {
      const double v = l.spring_law[k];
      if (!(std::isfinite(v) && (k % 3 == 1 ? v >= 0 : v > 0)))
        throw Error(f.path(), g + ": attribute spring_law holds an invalid value (" + std::to_string(v) + ")");
    }
  }
  if (f.has_attr(g, "volume_modulus")) {
    const auto v = f.attr_doubles(g, "volume_modulus");
    if (v.size() != 1 || !(std::isfinite(v[0]) && v[0] >= 0 && v[0] < 1e15))
      throw Error(f.path(), g + ": attribute volume_modulus must be one finite value >= 0 (Pa)");
    l.volume_modulus = v[0];
  }
  if (f.has_attr(g, "volume_group")) {
    const std::int64_t n = f.attr_int(g, "volume_group");
    if (n < 1 || n > 64) throw Error(f.path(), g + ": attribute volume_group must be in 1..64");
    l.volume_group = static_cast<int>(n);
  }
  if (f.has_attr(g, "guard_modulus")) {
    const auto v = f.attr_doubles(g, "guard_modulus");
    if (v.size() != 1 || !(std::isfinite(v[0]) && v[0] >= 0 && v[0] < 1e15))
      throw Error(f.path(), g + ": attribute guard_modulus must be one finite value >= 0 (Pa)");
    l.guard_modulus = v[0];
    const auto r = f.has_attr(g, "guard_ratio") ? f.attr_doubles(g, "guard_ratio") : std::vector<double>{};
    if (l.guard_modulus > 0 && (r.size() != 1 || !(r[0] > 0 && r[0] < 1)))
      throw Error(f.path(), g + ": attribute guard_ratio must be one value in (0, 1) where guard_modulus is set");
    if (l.guard_modulus > 0) l.guard_ratio = r[0];
  }
}
}  // namespace

namespace {
// the optional volume_tets dataset (Layer::volume_tets)
void read_volume_tets(const h5::File& f, const std::string& g, Layer& l) {
  if (f.exists(g + "/volume_tets")) FieldReader{f, g, nullptr}(l.volume_tets, "volume_tets", "n_volume_tets", "1", "");
}
}  // namespace

Layer ModelReader::layer(const std::string& name) const {
  const std::string g = "/layers/" + name;
  auto l = read_group<Layer>(file_, g);
  read_layer_attrs(file_, g, l);
  read_volume_tets(file_, g, l);
  return l;
}

Layer ModelReader::layer_fields(const std::string& name, const std::vector<std::string>& fields) const {
  const std::string g = "/layers/" + name;
  auto l = read_group<Layer>(file_, g, &fields);
  read_layer_attrs(file_, g, l);
  if (std::find(fields.begin(), fields.end(), "volume_tets") != fields.end()) read_volume_tets(file_, g, l);
  return l;
}

VecXi ModelReader::node_set(const std::string& name) const {
  const std::string p = "/layers/sets/" + name;
  if (!file_.exists(p)) throw Error(path(), "missing node set " + p);
  if (file_.dims(p).size() != 1) throw Error(path(), p + " must be 1-D");
  auto d = file_.read<std::int32_t>(p, nullptr);
  return Eigen::Map<VecXi>(d.data(), static_cast<Eigen::Index>(d.size()));
}

VesselTree ModelReader::vessels(const std::string& tissue) const {
  const std::string g = "/vessels/" + tissue;
  auto t = read_group<VesselTree>(file_, g);
  check_index_range(t.edges, t.nodes.rows(), path(), g + "/edges");
  check_index_range(t.branch_nodes, t.nodes.rows(), path(), g + "/branch_nodes");
  return t;
}

Tuning ModelReader::tuning(const std::string& tissue) const {
  const std::string g = "/tuning/" + tissue;
  auto t = read_group<Tuning>(file_, g);
  t.method = file_.attr_string(g, "method");
  t.seed = file_.attr_int(g, "seed");
  t.psi = file_.attr_double(g, "psi");
  t.evaluations = file_.attr_int(g, "evaluations");
  t.seconds = file_.attr_double(g, "seconds");
  return t;
}

std::map<std::string, Provenance> ModelReader::provenance() const {
  std::map<std::string, Provenance> out;
  for (const auto& stage : file_.children("/provenance")) {
    const std::string g = "/provenance/" + stage;
    Provenance p;
    p.tool_version = read_str_attr_or(file_, g, "tool_version", "");
    p.command_line = read_str_attr_or(file_, g, "command_line", "");
    p.inputs_json = read_str_attr_or(file_, g, "inputs", "{}");
    p.parameters_json = read_str_attr_or(file_, g, "parameters", "{}");
    p.time_utc = read_str_attr_or(file_, g, "time_utc", "");
    if (file_.has_attr(g, "seed")) p.seed = file_.attr_int(g, "seed");
    if (file_.has_attr(g, "wall_s")) p.wall_s = file_.attr_double(g, "wall_s");
    out[stage] = p;
  }
  return out;
}

// ---- writer ----------------------------------------------------------------

ModelWriter::ModelWriter(const std::string& target, Start start) : out_(target) {
  std::error_code ec;
  if (start == Start::update && fs::exists(target, ec)) {
    { ModelReader check(target); }  // refuse to update a file that is not ours
    fs::copy_file(target, out_.temp(), fs::copy_options::overwrite_existing, ec);
    if (ec) throw Error(target, "cannot copy for update: " + ec.message());
    file_.emplace(out_.temp(), h5::File::Mode::read_write);
  } else {
    file_.emplace(out_.temp(), h5::File::Mode::create);
  }
  file_->set_attr("/", "orthosim_format", format_version());
  file_->set_attr("/", "units", "SI: m, kg, s, Pa, N/m; positions in the image stack's physical frame");
}

ModelWriter::~ModelWriter() = default;  // file_ closes first, then out_ removes an uncommitted temp

void ModelWriter::commit() {
  file_->close();
  file_.reset();
  out_.commit();
}

void ModelWriter::write(const Volume& v) {
  const std::string g = "/volume";
  const std::size_t n = static_cast<std::size_t>(v.nx) * v.ny * v.nz;
  if (v.nx <= 0 || v.ny <= 0 || v.nz <= 0 || v.labels.size() != n)
    throw Error(out_.target(), "volume dimensions do not match its label count");
  file_->remove(g);
  file_->make_groups(g);
  file_->write<std::uint8_t>(g + "/labels", v.labels.data(),
                             {static_cast<std::uint64_t>(v.nz), static_cast<std::uint64_t>(v.ny),
                              static_cast<std::uint64_t>(v.nx)},
                             "label", "tissue labels [nz][ny][nx]; values index label_names");
  file_->set_attr(g, "spacing_m", std::vector<double>(v.spacing_m.begin(), v.spacing_m.end()));
  file_->set_attr(g, "origin_m", std::vector<double>(v.origin_m.begin(), v.origin_m.end()));
  file_->set_attr(g, "label_names", v.label_names);
}

void ModelWriter::write(const std::string& tissue, const Surface& s) {
  check_index_range(s.faces, s.vertices.rows(), out_.target(), "surface " + tissue + " faces");
  write_group(*file_, "/surfaces/" + tissue, s);
}

void ModelWriter::write(const std::string& tissue, const QuadSurface& q) {
  const std::string g = "/quads/" + tissue;
  if (static_cast<Eigen::Index>(q.nu) * q.nv != q.vertices.rows())
    throw Error(out_.target(), "quad surface " + tissue + ": nu*nv does not match the vertex count");
  check_index_range(q.quads, q.vertices.rows(), out_.target(), "quad surface " + tissue);
  write_group(*file_, g, q);
  file_->set_attr(g, "nu", static_cast<std::int64_t>(q.nu));
  file_->set_attr(g, "nv", static_cast<std::int64_t>(q.nv));
}

void ModelWriter::write_layer(const std::string& name, const Layer& l) {
  const std::string g = "/layers/" + name;
  write_group(*file_, g, l);
  file_->set_attr(g, "tissue", l.tissue);
  file_->set_attr(g, "kind", l.kind);
  file_->set_attr(g, "order", static_cast<std::int64_t>(l.order));
  file_->set_attr(g, "node_offset", l.node_offset);
  if (!l.spring_law.empty()) file_->set_attr(g, "spring_law", l.spring_law);
  if (l.volume_tets.rows() > 0) {
    if (l.volume_modulus <= 0) throw Error(out_.target(), g + ": volume_tets without a volume_modulus");
    FieldWriter{*file_, g}(l.volume_tets, "volume_tets", "n_volume_tets", "1",
                           "the volume term's tetrahedra (n x 4), global ids, where they are not tets");
  }
  if (l.volume_modulus > 0) {
    const Eigen::Index n = l.volume_tets.rows() > 0 ? l.volume_tets.rows() : l.tets.rows();
    if (l.volume_group < 1 || l.volume_group > 64 || n % l.volume_group != 0)
      throw Error(out_.target(), g + ": a volume_modulus needs tets (or volume_tets) in groups of volume_group (1..64)");
    file_->set_attr(g, "volume_modulus", std::vector<double>{l.volume_modulus});
    if (l.volume_group != 1) file_->set_attr(g, "volume_group", static_cast<std::int64_t>(l.volume_group));
  }
  if (l.guard_modulus > 0) {
    if (!(l.guard_ratio > 0 && l.guard_ratio < 1) || l.tets.rows() == 0)
      throw Error(out_.target(), g + ": a guard_modulus needs tets and a guard_ratio in (0, 1)");
    file_->set_attr(g, "guard_modulus", std::vector<double>{l.guard_modulus});
    file_->set_attr(g, "guard_ratio", std::vector<double>{l.guard_ratio});
  }
}

void ModelWriter::write_node_set(const std::string& name, const VecXi& ids) {
  file_->write<std::int32_t>("/layers/sets/" + name, ids.data(), {static_cast<std::uint64_t>(ids.size())},
                             "1", "global node ids");
}

void ModelWriter::write(const std::string& tissue, const VesselTree& t) {
  const std::string g = "/vessels/" + tissue;
  check_index_range(t.edges, t.nodes.rows(), out_.target(), g + "/edges");
  write_group(*file_, g, t);
}

void ModelWriter::write(const std::string& tissue, const Tuning& t) {
  const std::string g = "/tuning/" + tissue;
  write_group(*file_, g, t);
  file_->set_attr(g, "method", t.method);
  file_->set_attr(g, "seed", t.seed);
  file_->set_attr(g, "psi", t.psi);
  file_->set_attr(g, "evaluations", t.evaluations);
  file_->set_attr(g, "seconds", t.seconds);
}

void ModelWriter::write(const std::string& stage, const Provenance& p) {
  const std::string g = "/provenance/" + stage;
  file_->remove(g);
  file_->make_groups(g);
  file_->set_attr(g, "tool_version", p.tool_version);
  file_->set_attr(g, "command_line", p.command_line);
  file_->set_attr(g, "inputs", p.inputs_json);
  file_->set_attr(g, "parameters", p.parameters_json);
  file_->set_attr(g, "seed", p.seed);
  file_->set_attr(g, "time_utc", p.time_utc);
  file_->set_attr(g, "wall_s", p.wall_s);
}

}  // namespace orthosim
