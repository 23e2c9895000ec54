// STL reading (binary and ASCII) with exact vertex welding, and binary writing.
#include "libmodel/format/stl.h"

#include "libmodel/format/atomic.h"

#include <Eigen/Geometry>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <vector>

namespace orthosim {

namespace {

// welds bit-identical corners (+0 and -0 alike) into a Surface, numbering
// the vertices in the order they first appear. An open-addressing table of
// vertex ids (linear probing, kept at most half full) over the vertex array
// itself: a node-based std::unordered_map spent 3.3 s of remesh's read at
// 256^3 allocating one node per vertex.
class Welder {
 public:
  explicit Welder(std::size_t expected_vertices = 0) { rehash(std::max<std::size_t>(1024, 2 * expected_vertices)); }
  void add(const double c[3][3]) {
    int id[3];
    for (int k = 0; k < 3; ++k) id[k] = find_or_insert(c[k]);
    faces_.insert(faces_.end(), {id[0], id[1], id[2]});
  }
  Surface take() {
    Surface s;
    s.vertices.resize(static_cast<Eigen::Index>(xyz_.size() / 3), 3);
    for (std::size_t i = 0; i < xyz_.size(); ++i) s.vertices(i / 3, i % 3) = xyz_[i];
    s.faces.resize(static_cast<Eigen::Index>(faces_.size() / 3), 3);
    for (std::size_t i = 0; i < faces_.size(); ++i) s.faces(i / 3, i % 3) = faces_[i];
    return s;
  }

 private:
  static std::size_t hash(const double* p) {
    std::uint64_t h = 1469598103934665603ull, b;
    for (int d = 0; d < 3; ++d) {
      double v = p[d];
      if (v == 0) v = 0;  // -0 == +0
      std::memcpy(&b, &v, 8);
      h = (h ^ b) * 1099511628211ull;
      h ^= h >> 29;
    }
    return static_cast<std::size_t>(h);
  }
  int find_or_insert(const double* p) {
    const std::size_t n = xyz_.size() / 3;
    if (2 * (n + 1) > slots_.size()) rehash(2 * slots_.size());
    for (std::size_t h = hash(p) & mask_;; h = (h + 1) & mask_) {
      const std::int32_t v = slots_[h];
      if (v < 0) {
        slots_[h] = static_cast<std::int32_t>(n);
        xyz_.insert(xyz_.end(), {p[0], p[1], p[2]});
        return static_cast<int>(n);
      }
      const double* q = &xyz_[3 * static_cast<std::size_t>(v)];
      if (q[0] == p[0] && q[1] == p[1] && q[2] == p[2]) return v;
    }
  }
  void rehash(std::size_t size) {  // size: a power of two
    std::size_t cap = 1;
    while (cap < size) cap <<= 1;
    slots_.assign(cap, -1);
    mask_ = cap - 1;
    for (std::size_t v = 0; v < xyz_.size() / 3; ++v) {
      std::size_t h = hash(&xyz_[3 * v]) & mask_;
      while (slots_[h] >= 0) h = (h + 1) & mask_;
      slots_[h] = static_cast<std::int32_t>(v);
    }
  }
  std::vector<std::int32_t> slots_;
  std::size_t mask_ = 0;
  std::vector<double> xyz_;
  std::vector<int> faces_;
};

float read_f32(const char* p) {
  float f;
  std::memcpy(&f, p, 4);
  return f;
}

}  // namespace

Surface read_stl(const std::string& path) {
  std::error_code ec;
  // (a folder opened as a stream and failed reading: "internal error")
  if (std::filesystem::is_directory(path, ec)) throw Error(path, "is a folder, not an STL file");
  if (!std::filesystem::exists(path, ec)) throw Error(path, "cannot open STL file: no such file");
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(path, "cannot open STL file");
  std::string data((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (data.empty()) throw Error(path, "empty surface (empty file)");
  // binary when the size matches the triangle count in the header
  bool binary = false;
  std::uint32_t n = 0;
  if (data.size() >= 84) {
    std::memcpy(&n, data.data() + 80, 4);
    binary = data.size() == 84 + 50ull * n;
  }
  // a closed surface has about half as many vertices as triangles
  Welder w(binary ? n / 2 + 16 : 0);
  if (binary) {
    for (std::uint32_t t = 0; t < n; ++t) {
      const char* p = data.data() + 84 + 50ull * t + 12;
      double c[3][3];
      for (int k = 0; k < 3; ++k)
        for (int d = 0; d < 3; ++d) c[k][d] = read_f32(p + 12 * k + 4 * d);
      w.add(c);
    }
    return w.take();
  }
  std::size_t first = data.find_first_not_of(" \t\r\n");
  if (first == std::string::npos || data.compare(first, 5, "solid") != 0)
    throw Error(path, data.size() >= 84 ? "not an STL file (binary size does not match its triangle count)"
                                         : "not an STL file");
  std::istringstream s(data);
  std::string tok;
  double c[3][3];
  int corner = 0;
  long line_faces = 0;
  while (s >> tok) {
    if (tok == "vertex") {
      if (corner >= 3) throw Error(path, "ASCII STL facet " + std::to_string(line_faces) + " has more than 3 vertices");
      for (int d = 0; d < 3; ++d) {
        std::string v;
        if (!(s >> v)) throw Error(path, "truncated ASCII STL");
        char* end = nullptr;
        c[corner][d] = std::strtod(v.c_str(), &end);
        if (end == v.c_str() || *end) throw Error(path, "bad number '" + v + "' in ASCII STL");
      }
      ++corner;
    } else if (tok == "endloop") {
      if (corner != 3) throw Error(path, "ASCII STL facet " + std::to_string(line_faces) + " does not have 3 vertices");
      w.add(c);
      corner = 0;
      ++line_faces;
    }
  }
  if (corner != 0) throw Error(path, "truncated ASCII STL");
  return w.take();
}

void write_stl(const std::string& path, const Surface& s, const std::string& header) {
  check_output_file(path);
  AtomicFile out(path);
  {
    std::ofstream f(out.temp(), std::ios::binary);
    char head[80] = {0};
    std::snprintf(head, sizeof head, "%s", header.c_str());
    f.write(head, 80);
    const std::uint32_t n = static_cast<std::uint32_t>(s.faces.rows());
    f.write(reinterpret_cast<const char*>(&n), 4);
    for (Eigen::Index t = 0; t < s.faces.rows(); ++t) {
      const Eigen::Vector3d a = s.vertices.row(s.faces(t, 0)), b = s.vertices.row(s.faces(t, 1)),
                            c = s.vertices.row(s.faces(t, 2));
      Eigen::Vector3d nn = (b - a).cross(c - a);
      if (nn.norm() > 0) nn.normalize();
      float buf[12];
      for (int d = 0; d < 3; ++d) {
        buf[d] = static_cast<float>(nn(d));
        buf[3 + d] = static_cast<float>(a(d));
        buf[6 + d] = static_cast<float>(b(d));
        buf[9 + d] = static_cast<float>(c(d));
      }
      f.write(reinterpret_cast<const char*>(buf), 48);
      const std::uint16_t attr = 0;
      f.write(reinterpret_cast<const char*>(&attr), 2);
    }
    if (!f) throw Error(path, "write failed");
  }
  out.commit();
}

}  // namespace orthosim
