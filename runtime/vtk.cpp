#include "runtime/vtk.h"

#include "libmodel/format/atomic.h"

#include <bit>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <sstream>
#include <utility>

namespace orthosim::runtime {

static_assert(std::endian::native == std::endian::little, "the VTK writer declares LittleEndian");

namespace {

constexpr std::uint8_t kVtkLine = 3, kVtkQuad = 9;

// One array of a piece: XML header plus its payload.
struct Array {
  std::string type, name;
  int components = 1;
  std::string bytes;  // raw little-endian values
  std::size_t count = 0;
};

template <class T>
Array make_array(const std::string& type, const std::string& name, int components, const std::vector<T>& v) {
  Array a{type, name, components, std::string(reinterpret_cast<const char*>(v.data()), v.size() * sizeof(T)), v.size()};
  return a;
}

template <class T>
void ascii_values(std::ostream& out, const std::string& bytes) {
  const std::size_t n = bytes.size() / sizeof(T);
  const T* p = reinterpret_cast<const T*>(bytes.data());
  for (std::size_t i = 0; i < n; ++i) {
    if constexpr (sizeof(T) == 1)
      out << static_cast<int>(p[i]);
    else
      out << p[i];
    out << ((i + 1) % 12 == 0 ? '\n' : ' ');
  }
}

void write_ascii_array(std::ostream& out, const Array& a) {
  out << "<DataArray type=\"" << a.type << "\"";
  if (!a.name.empty()) out << " Name=\"" << a.name << "\"";
  out << " NumberOfComponents=\"" << a.components << "\" format=\"ascii\">\n";
  if (a.type == "Float64") ascii_values<double>(out, a.bytes);
  else if (a.type == "Int64") ascii_values<std::int64_t>(out, a.bytes);
  else ascii_values<std::uint8_t>(out, a.bytes);
  out << "\n</DataArray>\n";
}

// The data arrays of one VTK XML file: inline as ascii, or (binary) as
// references into the raw appended block that closes the file.
class ArrayWriter {
 public:
  ArrayWriter(std::ostream& os, bool binary) : os_(os), binary_(binary) {}
  void emit(const Array& a) {
    if (!binary_) {
      write_ascii_array(os_, a);
      return;
    }
    os_ << "<DataArray type=\"" << a.type << "\"";
    if (!a.name.empty()) os_ << " Name=\"" << a.name << "\"";
    os_ << " NumberOfComponents=\"" << a.components << "\" format=\"appended\" offset=\"" << offset_ << "\"/>\n";
    offset_ += sizeof(std::uint64_t) + a.bytes.size();
    appended_.push_back(&a);
  }
  // after the dataset's closing tag: the appended block, each array's byte count first
  void finish() {
    if (!binary_) return;
    os_ << "<AppendedData encoding=\"raw\">\n_";
    for (const Array* a : appended_) {
      const std::uint64_t nbytes = a->bytes.size();
      os_.write(reinterpret_cast<const char*>(&nbytes), sizeof nbytes);
      os_.write(a->bytes.data(), static_cast<std::streamsize>(a->bytes.size()));
    }
    os_ << "\n</AppendedData>\n";
  }

 private:
  std::ostream& os_;
  bool binary_;
  std::uint64_t offset_ = 0;
  std::vector<const Array*> appended_;
};

}  // namespace

VtkSeries::VtkSeries(const Model& m, std::string dir, std::string name, VtkOptions o)
    : dir_(std::move(dir)), name_(std::move(name)), opt_(o) {
  set_topology(m);
}

void VtkSeries::set_topology(const Model& m) {
  connectivity_.clear(), offsets_.clear(), types_.clear(), line_spring_.clear();
  n_quad_cells_ = 0;
  std::int64_t off = 0;
  if (opt_.surface) {
    for (std::int32_t q = 0; q < m.n_quads; ++q) {
      for (int k = 0; k < 4; ++k) connectivity_.push_back(m.quads[4 * static_cast<std::size_t>(q) + k]);
      offsets_.push_back(off += 4);
      types_.push_back(kVtkQuad);
    }
    n_quad_cells_ = m.n_quads;
  }
  if (opt_.springs) {
    for (std::int32_t s = 0; s < m.n_springs; ++s) {
      if (m.spring_tension[s]) continue;
      connectivity_.push_back(m.spring_a[s]);
      connectivity_.push_back(m.spring_b[s]);
      offsets_.push_back(off += 2);
      types_.push_back(kVtkLine);
      line_spring_.push_back(s);
    }
  }
}

std::string VtkSeries::pvd_path() const { return dir_ + "/" + name_ + ".pvd"; }

void VtkSeries::write(const Model& m, const State& s) {
  const auto n = static_cast<std::size_t>(m.n_nodes);
  std::vector<double> disp(3 * n), vel(s.v.begin(), s.v.end()), force(s.f.begin(), s.f.end());
  for (std::size_t i = 0; i < 3 * n; ++i) disp[i] = s.x[i] - m.rest_x[i];
  if (force.size() != 3 * n) force.assign(3 * n, 0);
  std::vector<std::uint8_t> pin(n);
  for (std::size_t i = 0; i < n; ++i) pin[i] = static_cast<std::uint8_t>(s.pin[i]);
  std::vector<double> strain(static_cast<std::size_t>(n_quad_cells_), 0.0);
  for (auto q : line_spring_) {
    const Vec3 d = load3(s.x.data(), m.spring_b[q]) - load3(s.x.data(), m.spring_a[q]);
    const Real rest = m.spring_rest[q];
    strain.push_back(rest > 0 ? norm(d) / rest - 1 : 0);
  }
  std::vector<double> points(s.x.begin(), s.x.end());

  std::vector<Array> point_data{make_array("Float64", "displacement", 3, disp), make_array("Float64", "velocity", 3, vel),
                                make_array("Float64", "force", 3, force), make_array("UInt8", "pin", 1, pin)};
  // with static colliders: each node's contact force (N, zero where none)
  std::vector<double> contact;
  if (s.obstacles) {
    if (s.contact_force.size() == 3 * n) contact.assign(s.contact_force.begin(), s.contact_force.end());
    else contact.assign(3 * n, 0);  // (before the first step)
    point_data.push_back(make_array("Float64", "contact_force", 3, contact));
  }
  std::vector<Array> cell_data{make_array("Float64", "strain", 1, strain)};
  Array pts = make_array("Float64", "", 3, points);
  std::vector<Array> cells{make_array("Int64", "connectivity", 1, connectivity_),
                           make_array("Int64", "offsets", 1, offsets_), make_array("UInt8", "types", 1, types_)};

  // (a char[64] cut names over 52 characters: every frame one file, exit 0)
  char digits[16];
  std::snprintf(digits, sizeof digits, "_%06d.vtu", frames());
  const std::string target = dir_ + "/" + name_ + digits;
  AtomicFile out(target);
  {
    std::ofstream os(out.temp(), std::ios::binary);
    if (!os) throw Error(target, "cannot write");
    os << std::setprecision(17);
    os << "<?xml version=\"1.0\"?>\n"
       << "<VTKFile type=\"UnstructuredGrid\" version=\"1.0\" byte_order=\"LittleEndian\" header_type=\"UInt64\">\n"
       << "<UnstructuredGrid>\n<FieldData>\n"
       << "<DataArray type=\"Float64\" Name=\"TimeValue\" NumberOfTuples=\"1\" format=\"ascii\">" << s.time
       << "</DataArray>\n</FieldData>\n"
       << "<Piece NumberOfPoints=\"" << n << "\" NumberOfCells=\"" << types_.size() << "\">\n";
    ArrayWriter arrays(os, opt_.binary);
    auto emit = [&](const Array& a) { arrays.emit(a); };
    os << "<PointData Vectors=\"velocity\">\n";
    for (const auto& a : point_data) emit(a);
    os << "</PointData>\n<CellData Scalars=\"strain\">\n";
    for (const auto& a : cell_data) emit(a);
    os << "</CellData>\n<Points>\n";
    emit(pts);
    os << "</Points>\n<Cells>\n";
    for (const auto& a : cells) emit(a);
    os << "</Cells>\n</Piece>\n</UnstructuredGrid>\n";
    arrays.finish();
    os << "</VTKFile>\n";
    os.flush();
    if (!os) throw Error(target, "write failed (disk full?)");
    bytes_ += static_cast<std::int64_t>(os.tellp());
  }
  out.commit();
  files_.emplace_back(s.time, name_ + digits);

  write_pvd(pvd_path(), files_);
}

namespace {

// f is <prefix><digits><extension>
bool is_frame(const std::string& f, const std::string& prefix, const std::string& extension) {
  if (f.size() <= prefix.size() + extension.size() || f.compare(0, prefix.size(), prefix) != 0 ||
      f.compare(f.size() - extension.size(), extension.size(), extension) != 0)
    return false;
  for (std::size_t i = prefix.size(); i < f.size() - extension.size(); ++i)
    if (f[i] < '0' || f[i] > '9') return false;
  return true;
}

}  // namespace

bool is_series_file(const std::string& name, const std::string& file) {
  if (file == name + "_vessels.vtp" || file == name + "_centrelines.vtp" || file == name + "_colliders.vtp") return true;
  for (const auto& [part, extension] : {std::pair<std::string, std::string>{"", ".vtu"}, {"_blood", ".vtp"}, {"_particles", ".vtp"}})
    if (file == name + part + ".pvd" || is_frame(file, name + part + "_", extension)) return true;
  return false;
}

int remove_series_frames(const std::string& dir, const std::string& prefix, const std::string& extension,
                         const std::string& pvd) {
  namespace fs = std::filesystem;
  std::vector<fs::path> stale;
  std::error_code ec;
  for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) {
    const std::string f = it->path().filename().string();
    if ((is_frame(f, prefix, extension) || (!pvd.empty() && f == pvd)) && it->is_regular_file(ec)) stale.push_back(it->path());
  }
  if (ec) throw Error(dir, "cannot list the output directory: " + ec.message());
  for (const auto& p : stale)
    if (!fs::remove(p, ec) && ec) throw Error(p.string(), "cannot remove a frame of an earlier run: " + ec.message());
  return static_cast<int>(stale.size());
}

void write_pvd(const std::string& path, const std::vector<std::pair<double, std::string>>& files) {
  std::ostringstream pvd;
  pvd << std::setprecision(17);
  pvd << "<?xml version=\"1.0\"?>\n<VTKFile type=\"Collection\" version=\"0.1\" byte_order=\"LittleEndian\">\n<Collection>\n";
  for (const auto& [t, f] : files) pvd << "<DataSet timestep=\"" << t << "\" group=\"\" part=\"0\" file=\"" << f << "\"/>\n";
  pvd << "</Collection>\n</VTKFile>\n";
  write_text_file(path, pvd.str());
}


void write_vtp(const std::string& path, std::span<const double> points, std::span<const std::int32_t> triangles,
               const std::vector<VtpArray>& point_data, bool binary, double time) {
  if (points.size() % 3 != 0 || triangles.size() % 3 != 0) throw Error(path, "vtp: points and triangles must be (n x 3)");
  const std::size_t n = points.size() / 3, nt = triangles.size() / 3;
  for (const auto& a : point_data)
    if (a.components < 1 || a.values.size() != n * static_cast<std::size_t>(a.components))
      throw Error(path, "vtp: point array '" + a.name + "' has " + std::to_string(a.values.size()) + " values for " +
                            std::to_string(n) + " points");
  std::vector<Array> pd;
  for (const auto& a : point_data) pd.push_back(make_array("Float64", a.name, a.components, a.values));
  const Array pts = make_array("Float64", "", 3, std::vector<double>(points.begin(), points.end()));
  std::vector<std::int64_t> conn, offs;
  if (nt > 0) {
    conn.assign(triangles.begin(), triangles.end());
    for (std::size_t t = 0; t < nt; ++t) offs.push_back(static_cast<std::int64_t>(3 * (t + 1)));
  } else {
    for (std::size_t i = 0; i < n; ++i) conn.push_back(static_cast<std::int64_t>(i)), offs.push_back(static_cast<std::int64_t>(i + 1));
  }
  const std::vector<Array> cells{make_array("Int64", "connectivity", 1, conn), make_array("Int64", "offsets", 1, offs)};
  AtomicFile out(path);
  {
    std::ofstream os(out.temp(), std::ios::binary);
    if (!os) throw Error(path, "cannot write");
    os << std::setprecision(17);
    os << "<?xml version=\"1.0\"?>\n"
       << "<VTKFile type=\"PolyData\" version=\"1.0\" byte_order=\"LittleEndian\" header_type=\"UInt64\">\n"
       << "<PolyData>\n<FieldData>\n"
       << "<DataArray type=\"Float64\" Name=\"TimeValue\" NumberOfTuples=\"1\" format=\"ascii\">" << time
       << "</DataArray>\n</FieldData>\n"
       << "<Piece NumberOfPoints=\"" << n << "\" NumberOfVerts=\"" << (nt > 0 ? 0 : n)
       << "\" NumberOfLines=\"0\" NumberOfStrips=\"0\" NumberOfPolys=\"" << nt << "\">\n";
    ArrayWriter arrays(os, binary);
    auto emit = [&](const Array& a) { arrays.emit(a); };
    os << "<PointData>\n";
    for (const auto& a : pd) emit(a);
    os << "</PointData>\n<Points>\n";
    emit(pts);
    os << "</Points>\n" << (nt > 0 ? "<Polys>\n" : "<Verts>\n");
    for (const auto& a : cells) emit(a);
    os << (nt > 0 ? "</Polys>\n" : "</Verts>\n") << "</Piece>\n</PolyData>\n";
    arrays.finish();
    os << "</VTKFile>\n";
    os.flush();
    if (!os) throw Error(path, "write failed (disk full?)");
  }
  out.commit();
}

}  // namespace orthosim::runtime
