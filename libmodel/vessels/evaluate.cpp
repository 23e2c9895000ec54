// Checks and comparisons shared by the stage, the tests and the benchmark:
// mesh topology, distance to the label's voxel boundary, the label's closed
// surface (marching tetrahedra), centreline errors against a truth tree, and
// the STL/OBJ writers.
#include "libmodel/format/stl.h"
#include "libmodel/vessels/detail.h"

#include <Eigen/Dense>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <map>
#include <numeric>
#include <sstream>
#include <unordered_map>

namespace orthosim {

using namespace vessels_detail;

// ---- mesh topology -------------------------------------------------------------------

MeshCheck check_mesh(const MatX3d& V, const MatX4i& Q, const MatX3i& T) {
  MeshCheck c;
  std::vector<std::vector<int>> faces;
  for (Eigen::Index i = 0; i < Q.rows(); ++i) faces.push_back({Q(i, 0), Q(i, 1), Q(i, 2), Q(i, 3)});
  for (Eigen::Index i = 0; i < T.rows(); ++i) faces.push_back({T(i, 0), T(i, 1), T(i, 2)});
  const int nv = static_cast<int>(V.rows());
  std::map<std::pair<int, int>, std::vector<int>> edges;  // undirected edge -> +-(face+1) by direction
  for (std::size_t f = 0; f < faces.size(); ++f) {
    const auto& F = faces[f];
    std::vector<int> s = F;
    std::sort(s.begin(), s.end());
    bool degenerate = std::adjacent_find(s.begin(), s.end()) != s.end();
    Eigen::Vector3d area = Eigen::Vector3d::Zero();
    for (std::size_t i = 1; i + 1 < F.size(); ++i)
      area += (V.row(F[i]) - V.row(F[0])).transpose().cross((V.row(F[i + 1]) - V.row(F[0])).transpose());
    if (area.norm() <= 0) degenerate = true;
    c.degenerate_faces += degenerate;
    for (std::size_t i = 0; i < F.size(); ++i) {
      const int a = F[i], b = F[(i + 1) % F.size()];
      edges[std::minmax(a, b)].push_back(a < b ? static_cast<int>(f) + 1 : -static_cast<int>(f) - 1);
      if (i >= 1 && i + 1 < F.size())
        c.volume_m3 += V.row(F[0]).dot(V.row(F[i]).cross(V.row(F[i + 1]))) / 6;
    }
  }
  // components (faces joined by edges)
  std::vector<int> parent(faces.size());
  std::iota(parent.begin(), parent.end(), 0);
  auto find = [&](int x) {
    while (parent[x] != x) x = parent[x] = parent[parent[x]];
    return x;
  };
  for (const auto& [e, fs] : edges) {
    if (fs.size() == 1) ++c.boundary_edges;
    if (fs.size() > 2) ++c.nonmanifold_edges;
    if (fs.size() == 2 && ((fs[0] > 0) == (fs[1] > 0))) ++c.misoriented_edges;
    for (std::size_t i = 1; i < fs.size(); ++i) parent[find(std::abs(fs[i]) - 1)] = find(std::abs(fs[0]) - 1);
  }
  std::map<int, int> comp_id;
  for (std::size_t f = 0; f < faces.size(); ++f) comp_id.emplace(find(static_cast<int>(f)), static_cast<int>(comp_id.size()));
  c.components = static_cast<int>(comp_id.size());
  std::vector<std::int64_t> cv(c.components, 0), ce(c.components, 0), cf(c.components, 0);
  std::vector<int> vcomp(nv, -1);
  for (std::size_t f = 0; f < faces.size(); ++f) {
    const int k = comp_id[find(static_cast<int>(f))];
    ++cf[k];
    for (int v : faces[f]) vcomp[v] = k;
  }
  for (int v = 0; v < nv; ++v)
    if (vcomp[v] >= 0) ++cv[vcomp[v]];
  for (const auto& [e, fs] : edges) ++ce[comp_id[find(std::abs(fs[0]) - 1)]];
  for (int k = 0; k < c.components; ++k) c.euler.push_back(static_cast<int>(cv[k] - ce[k] + cf[k]));
  // vertex links: the faces around a vertex form one fan
  std::vector<std::vector<std::pair<int, int>>> link(nv);
  for (const auto& F : faces)
    for (std::size_t i = 0; i < F.size(); ++i)
      link[F[i]].push_back({F[(i + F.size() - 1) % F.size()], F[(i + 1) % F.size()]});
  for (int v = 0; v < nv; ++v) {
    if (link[v].empty()) continue;
    std::map<int, std::vector<int>> g;
    for (const auto& [a, b] : link[v]) g[a].push_back(b), g[b].push_back(a);
    bool bad = false;
    for (const auto& [a, nb] : g) bad |= nb.size() > 2;
    // connected?
    std::map<int, int> seen;
    std::vector<int> stack{g.begin()->first};
    seen[stack[0]] = 1;
    while (!stack.empty()) {
      const int a = stack.back();
      stack.pop_back();
      for (int b : g[a])
        if (!seen.count(b)) seen[b] = 1, stack.push_back(b);
    }
    bad |= seen.size() != g.size();
    c.nonmanifold_vertices += bad;
  }
  return c;
}

Surface tube_triangles(const VesselTree& t) {
  Surface s;
  s.vertices = t.tube_vertices;
  s.faces.resize(2 * t.tube_quads.rows() + t.tube_tris.rows(), 3);
  Eigen::Index k = 0;
  for (Eigen::Index i = 0; i < t.tube_quads.rows(); ++i) {
    const int a = t.tube_quads(i, 0), b = t.tube_quads(i, 1), c = t.tube_quads(i, 2), d = t.tube_quads(i, 3);
    const double ac = (t.tube_vertices.row(a) - t.tube_vertices.row(c)).squaredNorm();
    const double bd = (t.tube_vertices.row(b) - t.tube_vertices.row(d)).squaredNorm();
    if (ac <= bd) {
      s.faces.row(k++) << a, b, c;
      s.faces.row(k++) << a, c, d;
    } else {
      s.faces.row(k++) << a, b, d;
      s.faces.row(k++) << b, c, d;
    }
  }
  for (Eigen::Index i = 0; i < t.tube_tris.rows(); ++i) s.faces.row(k++) = t.tube_tris.row(i);
  return s;
}

// ---- distance to the label's voxel boundary -------------------------------------------

VecXd distance_to_label_boundary(const Volume& v, int label, const MatX3d& points, double max_m) {
  struct Face {
    Eigen::Vector3d c;
    int axis;
  };
  std::vector<Face> faces;
  const int n[3] = {v.nx, v.ny, v.nz};
  // the label's bounding box (plus one voxel): no face of the label lies outside it
  int blo[3] = {v.nx, v.ny, v.nz}, bhi[3] = {-1, -1, -1};
  for (int z = 0; z < v.nz; ++z)
    for (int y = 0; y < v.ny; ++y) {
      const std::uint8_t* row = v.labels.data() + v.index(0, y, z);
      int x0 = -1, x1 = -1;
      for (int x = 0; x < v.nx; ++x)
        if (row[x] == label) {
          if (x0 < 0) x0 = x;
          x1 = x;
        }
      if (x0 < 0) continue;
      blo[0] = std::min(blo[0], x0), bhi[0] = std::max(bhi[0], x1);
      blo[1] = std::min(blo[1], y), bhi[1] = std::max(bhi[1], y);
      blo[2] = std::min(blo[2], z), bhi[2] = std::max(bhi[2], z);
    }
  for (int a = 0; a < 3; ++a) blo[a] = std::max(0, blo[a] - 1), bhi[a] = std::min(n[a] - 1, bhi[a] + 1);
  for (int z = blo[2]; z <= bhi[2]; ++z)
    for (int y = blo[1]; y <= bhi[1]; ++y)
      for (int x = blo[0]; x <= bhi[0]; ++x) {
        const bool in = v.at(x, y, z) == label;
        const int c[3] = {x, y, z};
        for (int a = 0; a < 3; ++a) {
          if (c[a] + 1 >= n[a]) continue;
          const int d[3] = {x + (a == 0), y + (a == 1), z + (a == 2)};
          const bool in2 = v.at(d[0], d[1], d[2]) == label;
          if (in == in2) continue;
          Eigen::Vector3d p = v.position(x, y, z);
          p(a) += 0.5 * v.spacing_m[a];
          faces.push_back({p, a});
        }
      }
  VecXd out = VecXd::Constant(points.rows(), max_m);
  if (faces.empty()) return out;
  // grid of face centres, cubic cells twice the voxel's geometric-mean size: the
  // rings below grow by a cell along every axis, and with cells of two voxels per
  // axis a strongly anisotropic voxel (0.01 x 0.3 x 1 mm) made each ring 30-100x
  // longer along the coarse axes than its guaranteed radius along the fine one: the
  // vessels stage ran for minutes (the same faces are found: the search is exact)
  const double cube = 2 * std::cbrt(v.spacing_m[0] * v.spacing_m[1] * v.spacing_m[2]);
  const Eigen::Vector3d cell = Eigen::Vector3d::Constant(cube);
  const double cmin = cube;
  // the largest half-diagonal of a face: a face whose centre is d away is at least d - fh away
  std::array<double, 3> hs = v.spacing_m;
  std::sort(hs.begin(), hs.end());
  const double fh = 0.5 * std::sqrt(hs[1] * hs[1] + hs[2] * hs[2]);
  Eigen::Vector3d lo = faces[0].c, hi = faces[0].c;
  for (const Face& f : faces) lo = lo.cwiseMin(f.c), hi = hi.cwiseMax(f.c);
  const Eigen::Vector3i dim = ((hi - lo).cwiseQuotient(cell).array().floor().cast<int>() + 1).matrix();
  auto cell_of = [&](const Eigen::Vector3d& p) {
    return Eigen::Vector3i(static_cast<int>(std::floor((p.x() - lo.x()) / cell.x())),
                           static_cast<int>(std::floor((p.y() - lo.y()) / cell.y())),
                           static_cast<int>(std::floor((p.z() - lo.z()) / cell.z())));
  };
  std::vector<int> start(static_cast<std::size_t>(dim.prod()) + 1, 0);
  auto lin = [&](const Eigen::Vector3i& c) { return (static_cast<std::size_t>(c.z()) * dim.y() + c.y()) * dim.x() + c.x(); };
  for (const Face& f : faces) ++start[lin(cell_of(f.c)) + 1];
  std::partial_sum(start.begin(), start.end(), start.begin());
  std::vector<int> order(faces.size()), fill(start.begin(), start.end() - 1);
  for (std::size_t i = 0; i < faces.size(); ++i) order[fill[lin(cell_of(faces[i].c))]++] = static_cast<int>(i);
  const std::array<double, 3> h = v.spacing_m;
  auto face_distance = [&](const Face& f, const Eigen::Vector3d& p) {
    Eigen::Vector3d d = p - f.c;
    for (int a = 0; a < 3; ++a)
      if (a != f.axis) d(a) = std::max(0.0, std::abs(d(a)) - 0.5 * h[a]);
    return d.norm();
  };
  tbb::parallel_for(Eigen::Index(0), points.rows(), [&](Eigen::Index i) {
    const Eigen::Vector3d p = points.row(i).transpose();
    const Eigen::Vector3i c = cell_of(p);
    double best = max_m;
    for (int ring = 0;; ++ring) {
      for (int z = c.z() - ring; z <= c.z() + ring; ++z)
        for (int y = c.y() - ring; y <= c.y() + ring; ++y)
          for (int x = c.x() - ring; x <= c.x() + ring; ++x) {
            if (std::max({std::abs(x - c.x()), std::abs(y - c.y()), std::abs(z - c.z())}) != ring) continue;
            if (x < 0 || y < 0 || z < 0 || x >= dim.x() || y >= dim.y() || z >= dim.z()) continue;
            const std::size_t l = lin({x, y, z});
            for (int k = start[l]; k < start[l + 1]; ++k) best = std::min(best, face_distance(faces[order[k]], p));
          }
      // every face centre within ring * cmin of p has been seen
      if (best <= ring * cmin - fh || ring * cmin > max_m + cell.maxCoeff() ||
          ring > dim.maxCoeff() + std::abs(c.maxCoeff()) + std::abs(c.minCoeff()))
        break;
    }
    out(i) = best;
  });
  return out;
}

// ---- the label's closed surface ----------------------------------------------------------

Surface label_surface(const Volume& v, int label, double smooth_vox) {
  int lo[3] = {v.nx, v.ny, v.nz}, hi[3] = {-1, -1, -1};
  for (int z = 0; z < v.nz; ++z)
    for (int y = 0; y < v.ny; ++y)
      for (int x = 0; x < v.nx; ++x)
        if (v.at(x, y, z) == label) {
          const int c[3] = {x, y, z};
          for (int a = 0; a < 3; ++a) lo[a] = std::min(lo[a], c[a]), hi[a] = std::max(hi[a], c[a]);
        }
  Surface s;
  if (hi[0] < 0) return s;
  const int pad = 2 + static_cast<int>(std::ceil(3 * smooth_vox));
  int n[3];
  for (int a = 0; a < 3; ++a) lo[a] -= pad, hi[a] += pad, n[a] = hi[a] - lo[a] + 1;
  auto idx = [&](int x, int y, int z) { return (static_cast<std::size_t>(z) * n[1] + y) * n[0] + x; };
  std::vector<double> f(static_cast<std::size_t>(n[0]) * n[1] * n[2], 0.0);
  for (int z = 0; z < n[2]; ++z)
    for (int y = 0; y < n[1]; ++y)
      for (int x = 0; x < n[0]; ++x) {
        const int X = x + lo[0], Y = y + lo[1], Z = z + lo[2];
        if (X >= 0 && Y >= 0 && Z >= 0 && X < v.nx && Y < v.ny && Z < v.nz && v.at(X, Y, Z) == label)
          f[idx(x, y, z)] = 1;
      }
  if (smooth_vox > 0) {  // separable Gaussian, sigma in voxels along each axis
    const int w = static_cast<int>(std::ceil(3 * smooth_vox));
    std::vector<double> k(2 * w + 1);
    double ks = 0;
    for (int i = -w; i <= w; ++i) ks += k[i + w] = std::exp(-0.5 * i * i / (smooth_vox * smooth_vox));
    for (double& x : k) x /= ks;
    std::vector<double> g(f.size());
    const std::size_t stride[3] = {1, static_cast<std::size_t>(n[0]), static_cast<std::size_t>(n[0]) * n[1]};
    for (int a = 0; a < 3; ++a) {
      for (int z = 0; z < n[2]; ++z)
        for (int y = 0; y < n[1]; ++y)
          for (int x = 0; x < n[0]; ++x) {
            const int c[3] = {x, y, z};
            double acc = 0;
            for (int i = -w; i <= w; ++i) {
              const int q = c[a] + i;
              if (q < 0 || q >= n[a]) continue;
              acc += k[i + w] * f[idx(x, y, z) + static_cast<std::ptrdiff_t>(i) * static_cast<std::ptrdiff_t>(stride[a])];
            }
            g[idx(x, y, z)] = acc;
          }
      f.swap(g);
    }
  }
  for (double& x : f) {
    x -= 0.5;
    if (x == 0) x = 1e-12;  // no vertex exactly on the level set
  }
  // marching tetrahedra on the Freudenthal decomposition of each cube
  static const int tets[6][4] = {{0, 1, 3, 7}, {0, 3, 2, 7}, {0, 2, 6, 7}, {0, 6, 4, 7}, {0, 4, 5, 7}, {0, 5, 1, 7}};
  std::unordered_map<std::uint64_t, int> vid;
  std::vector<Eigen::Vector3d> verts;
  std::vector<std::array<int, 3>> tris;
  auto pos = [&](std::size_t i) {
    const int x = static_cast<int>(i % n[0]), y = static_cast<int>((i / n[0]) % n[1]), z = static_cast<int>(i / n[0] / n[1]);
    return v.position(x + lo[0], y + lo[1], z + lo[2]);
  };
  auto edge_vertex = [&](std::size_t a, std::size_t b) {
    const std::uint64_t key = std::min(a, b) * 0x100000000ull + std::max(a, b);
    auto it = vid.find(key);
    if (it != vid.end()) return it->second;
    const double t = f[a] / (f[a] - f[b]);
    verts.push_back(pos(a) + t * (pos(b) - pos(a)));
    return vid[key] = static_cast<int>(verts.size()) - 1;
  };
  auto emit = [&](int a, int b, int c, const Eigen::Vector3d& in, const Eigen::Vector3d& out) {
    const Eigen::Vector3d nrm = (verts[b] - verts[a]).cross(verts[c] - verts[a]);
    if (nrm.dot(out - in) < 0) std::swap(b, c);
    tris.push_back({a, b, c});
  };
  for (int z = 0; z + 1 < n[2]; ++z)
    for (int y = 0; y + 1 < n[1]; ++y)
      for (int x = 0; x + 1 < n[0]; ++x) {
        std::size_t cv[8];
        int inside = 0;
        for (int c = 0; c < 8; ++c) {
          cv[c] = idx(x + (c & 1), y + ((c >> 1) & 1), z + ((c >> 2) & 1));
          inside += f[cv[c]] > 0;
        }
        if (inside == 0 || inside == 8) continue;
        for (const auto& T : tets) {
          std::vector<std::size_t> in, out;
          for (int c : T) (f[cv[c]] > 0 ? in : out).push_back(cv[c]);
          if (in.empty() || out.empty()) continue;
          Eigen::Vector3d ci = Eigen::Vector3d::Zero(), co = Eigen::Vector3d::Zero();
          for (auto i : in) ci += pos(i);
          for (auto o : out) co += pos(o);
          ci /= static_cast<double>(in.size()), co /= static_cast<double>(out.size());
          if (in.size() == 1 || out.size() == 1) {
            const std::size_t lone = in.size() == 1 ? in[0] : out[0];
            const auto& others = in.size() == 1 ? out : in;
            emit(edge_vertex(lone, others[0]), edge_vertex(lone, others[1]), edge_vertex(lone, others[2]), ci, co);
          } else {
            const int a = edge_vertex(in[0], out[0]), b = edge_vertex(in[0], out[1]), c = edge_vertex(in[1], out[1]),
                      d = edge_vertex(in[1], out[0]);
            emit(a, b, c, ci, co);
            emit(a, c, d, ci, co);
          }
        }
      }
  s.vertices.resize(static_cast<Eigen::Index>(verts.size()), 3);
  for (std::size_t i = 0; i < verts.size(); ++i) s.vertices.row(static_cast<Eigen::Index>(i)) = verts[i].transpose();
  s.faces.resize(static_cast<Eigen::Index>(tris.size()), 3);
  for (std::size_t i = 0; i < tris.size(); ++i) s.faces.row(static_cast<Eigen::Index>(i)) << tris[i][0], tris[i][1], tris[i][2];
  return s;
}

// ---- centreline comparison -------------------------------------------------------------

namespace {

struct Poly {
  std::vector<Eigen::Vector3d> a, b;
  std::vector<double> ra, rb;
};

Poly polyline(const MatX3d& nodes, const MatX2i& edges, const VecXd* radii) {
  Poly p;
  for (Eigen::Index e = 0; e < edges.rows(); ++e) {
    p.a.push_back(nodes.row(edges(e, 0)).transpose());
    p.b.push_back(nodes.row(edges(e, 1)).transpose());
    p.ra.push_back(radii ? (*radii)(edges(e, 0)) : 0);
    p.rb.push_back(radii ? (*radii)(edges(e, 1)) : 0);
  }
  if (edges.rows() == 0)
    for (Eigen::Index i = 0; i < nodes.rows(); ++i) {
      p.a.push_back(nodes.row(i).transpose()), p.b.push_back(nodes.row(i).transpose());
      p.ra.push_back(radii ? (*radii)(i) : 0), p.rb.push_back(radii ? (*radii)(i) : 0);
    }
  return p;
}

// distance from q to the polyline and the radius there
double nearest(const Poly& p, const Eigen::Vector3d& q, double* r) {
  double best = 1e300;
  for (std::size_t i = 0; i < p.a.size(); ++i) {
    double t = 0;
    const double d = segment_distance(q, p.a[i], p.b[i], &t);
    if (d < best) best = d, *r = p.ra[i] + t * (p.rb[i] - p.ra[i]);
  }
  return best;
}

CentrelineError compare(const MatX3d& en, const MatX2i& ee, const VecXd* er, const VesselTree& truth) {
  CentrelineError c;
  const Poly tp = polyline(truth.nodes, truth.edges, &truth.radii);
  const Poly ep = polyline(en, ee, er);
  const Eigen::Index ne = en.rows(), nt = truth.nodes.rows();
  std::vector<double> d(ne), rt(ne), dt(nt), re(nt);
  tbb::parallel_for(Eigen::Index(0), ne, [&](Eigen::Index i) { d[i] = nearest(tp, en.row(i).transpose(), &rt[i]); });
  tbb::parallel_for(Eigen::Index(0), nt, [&](Eigen::Index i) { dt[i] = nearest(ep, truth.nodes.row(i).transpose(), &re[i]); });
  int in_e = 0, in_t = 0;
  std::vector<double> rel;
  for (Eigen::Index i = 0; i < ne; ++i) {
    c.mean_m += d[i] / static_cast<double>(ne);
    c.max_m = std::max(c.max_m, d[i]);
    in_e += d[i] <= rt[i];
    if (er) rel.push_back(std::abs((*er)(i) - rt[i]) / rt[i]);
  }
  for (Eigen::Index i = 0; i < nt; ++i) {
    c.truth_mean_m += dt[i] / static_cast<double>(nt);
    c.truth_max_m = std::max(c.truth_max_m, dt[i]);
    in_t += dt[i] <= (er ? re[i] : truth.radii(i));
  }
  c.overlap_extracted = ne ? static_cast<double>(in_e) / static_cast<double>(ne) : 0;
  c.overlap_truth = nt ? static_cast<double>(in_t) / static_cast<double>(nt) : 0;
  if (!rel.empty()) {
    c.radius_mean_rel = std::accumulate(rel.begin(), rel.end(), 0.0) / static_cast<double>(rel.size());
    std::sort(rel.begin(), rel.end());
    c.radius_max_rel = rel.back();
    c.radius_p95_rel = rel[std::min(rel.size() - 1, static_cast<std::size_t>(0.95 * static_cast<double>(rel.size())))];
  }
  return c;
}

}  // namespace

CentrelineError compare_centrelines(const VesselTree& extracted, const VesselTree& truth) {
  return compare(extracted.nodes, extracted.edges, &extracted.radii, truth);
}

CentrelineError compare_centrelines(const MatX3d& nodes, const MatX2i& edges, const VesselTree& truth) {
  return compare(nodes, edges, nullptr, truth);
}

// ---- files -------------------------------------------------------------------------------

void write_tube_stl(const std::string& path, const VesselTree& t) {
  write_stl(path, tube_triangles(t), "orthosim vessel tube, binary STL, metres");
}

void write_tube_obj(const std::string& path, const VesselTree& t) {
  check_output_file(path);
  AtomicFile out(path);
  {
    std::ofstream f(out.temp());
    f.precision(9);
    f << "# orthosim vessel tube (metres): quads and triangles, outward\n";
    for (Eigen::Index i = 0; i < t.tube_vertices.rows(); ++i)
      f << "v " << t.tube_vertices(i, 0) << " " << t.tube_vertices(i, 1) << " " << t.tube_vertices(i, 2) << "\n";
    for (Eigen::Index i = 0; i < t.tube_quads.rows(); ++i)
      f << "f " << t.tube_quads(i, 0) + 1 << " " << t.tube_quads(i, 1) + 1 << " " << t.tube_quads(i, 2) + 1 << " "
        << t.tube_quads(i, 3) + 1 << "\n";
    for (Eigen::Index i = 0; i < t.tube_tris.rows(); ++i)
      f << "f " << t.tube_tris(i, 0) + 1 << " " << t.tube_tris(i, 1) + 1 << " " << t.tube_tris(i, 2) + 1 << "\n";
    if (!f) throw Error(path, "write failed");
  }
  out.commit();
}

void write_centreline_obj(const std::string& path, const VesselTree& t) {
  check_output_file(path);
  AtomicFile out(path);
  {
    std::ofstream f(out.temp());
    f.precision(9);
    f << "# orthosim vessel centreline (metres): one polyline per branch\n";
    for (Eigen::Index i = 0; i < t.nodes.rows(); ++i)
      f << "v " << t.nodes(i, 0) << " " << t.nodes(i, 1) << " " << t.nodes(i, 2) << "\n";
    for (Eigen::Index b = 0; b + 1 < t.branch_offsets.size(); ++b) {
      f << "l";
      for (int k = t.branch_offsets(b); k < t.branch_offsets(b + 1); ++k) f << " " << t.branch_nodes(k) + 1;
      f << "\n";
    }
    if (!f) throw Error(path, "write failed");
  }
  out.commit();
}

}  // namespace orthosim
