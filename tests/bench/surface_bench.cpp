// surface_bench: extraction of the phantom's tissues from a 256^3 label
// volume at several settings (Gaussian on/off, Taubin on/off, decimation
// levels), with faces, per-phase times and the error against the analytic
// interfaces (mean and Hausdorff in voxels of the smallest spacing). With
// ORTHOSIM_WITH_VTK_PEER: VTK's flying edges (vtkDiscreteFlyingEdges3D on the
// label image, vtkFlyingEdges3D on the 0/1 image) side by side.
//
//   build/tests/surface_bench [--benchmark_filter=...]
// Threads: all cores (set ORTHOSIM_BENCH_THREADS=n to limit, e.g. 2).
//   surface_bench --results=FILE.json [--quick]   the harness rows (orthosim bench; 2 threads):
//     phantom 256^3 (quick 128^3 at twice the spacing); per tissue (skin, muscle, bone) the binary
//     extraction (whole extract_surface call) and VTK vtkFlyingEdges3D on the same 0/1 image timed in
//     alternation; the skin at the other settings (Gaussian 0.7, defaults with Taubin; full: decimated
//     to 50 000 faces by each edge-collapse cost). Error = Hausdorff distance to the analytic interface in voxels of the smallest
//     spacing (goal <= 2, issue 3; from 20 000 surface samples, quick 4 000), the mean and faces in extra.
#include "libmodel/phantom/phantom.h"
#include "libmodel/surface/surface.h"
#include "tests/bench/bench_results.h"

#include <benchmark/benchmark.h>
#include <tbb/global_control.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <memory>

#ifdef ORTHOSIM_HAVE_VTK_PEER
#include <vtkCellArray.h>
#include <vtkDiscreteFlyingEdges3D.h>
#include <vtkFlyingEdges3D.h>
#include <vtkImageData.h>
#include <vtkNew.h>
#include <vtkPoints.h>
#include <vtkPolyData.h>
#endif

using namespace orthosim;

namespace {

int g_size = 256;         // the phantom's voxels per side (--results --quick: 128)
long g_samples = 20000;   // surface samples for the distance (--results --quick: 4000)

struct Fixture {
  PhantomOptions p;
  Volume v;
  std::vector<int> parents;
  Fixture() {
    p.nx = p.ny = p.nz = g_size;
    p.spacing_m = {0.3e-3 * 256 / g_size, 0.3e-3 * 256 / g_size, 0.5e-3 * 256 / g_size};
    const auto t0 = std::chrono::steady_clock::now();
    v = phantom_labels(p);
    parents = label_parents(v, phantom_tissue_table());
    std::fprintf(stderr, "phantom 256^3 labels: %.2f s\n",
                 std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  }
};

const Fixture& fixture() {
  static const Fixture f;
  return f;
}

std::unique_ptr<tbb::global_control> thread_limit() {
  const char* e = std::getenv("ORTHOSIM_BENCH_THREADS");
  if (!e || std::atoi(e) <= 0) return nullptr;
  return std::make_unique<tbb::global_control>(tbb::global_control::max_allowed_parallelism, std::atoi(e));
}

// mean and max distance (voxels of the smallest spacing) from a subsample of
// the surface's vertices, face centroids and edge midpoints to the analytic interface
std::pair<double, double> surface_error(const Surface& s, const std::string& tissue) {
  const Fixture& f = fixture();
  const MatX3d all = surface_samples(s);
  const Eigen::Index step = std::max<Eigen::Index>(1, all.rows() / g_samples);
  MatX3d sub((all.rows() + step - 1) / step, 3);
  for (Eigen::Index i = 0; i < sub.rows(); ++i) sub.row(i) = all.row(i * step);
  const VecXd d = phantom_interface_distances(f.p, tissue, sub);
  const double vox = *std::min_element(f.v.spacing_m.begin(), f.v.spacing_m.end());
  return {d.mean() / vox, d.maxCoeff() / vox};
}
void error_counters(benchmark::State& state, const Surface& s, const std::string& tissue) {
  const auto [mean, haus] = surface_error(s, tissue);
  state.counters["mean_vox"] = mean;
  state.counters["hausdorff_vox"] = haus;
}

// args: tissue index, sigma x 10, Taubin iterations, target faces
const char* kTissues[] = {"skin", "muscle", "bone"};

void BM_Surface(benchmark::State& state) {
  const auto limit = thread_limit();
  const Fixture& f = fixture();
  const std::string tissue = kTissues[state.range(0)];
  SurfaceOptions o;
  o.sigma_vox = state.range(1) / 10.0;
  o.smooth_iterations = static_cast<int>(state.range(2));
  o.target_faces = state.range(3);
  o.check_self_intersections = false;
  const std::vector<int> labels = solid_label_set(f.v, tissue, f.parents);
  SurfaceResult r;
  double solid = 0, field = 0, extract = 0, smooth = 0, decimate = 0, check = 0;
  for (auto _ : state) {
    r = extract_surface(f.v, labels, o);
    solid += r.metrics.solid_s, field += r.metrics.field_s, extract += r.metrics.extract_s;
    smooth += r.metrics.smooth_s, decimate += r.metrics.decimate_s, check += r.metrics.check_s;
  }
  const double n = static_cast<double>(state.iterations());
  state.SetLabel(tissue);
  state.counters["faces"] = static_cast<double>(r.metrics.faces);
  state.counters["extracted"] = static_cast<double>(r.metrics.extracted_faces);
  state.counters["solid_ms"] = 1e3 * solid / n;
  state.counters["field_ms"] = 1e3 * field / n;
  state.counters["extract_ms"] = 1e3 * extract / n;
  state.counters["smooth_ms"] = 1e3 * smooth / n;
  state.counters["decimate_ms"] = 1e3 * decimate / n;
  state.counters["check_ms"] = 1e3 * check / n;
  error_counters(state, r.surface, tissue);
}
// binary (no Gaussian, no Taubin): the same work as flying edges on a 0/1 image
BENCHMARK(BM_Surface)->Args({0, 0, 0, 0})->Args({1, 0, 0, 0})->Args({2, 0, 0, 0})->Unit(benchmark::kMillisecond);
// the defaults, then without Taubin, then decimated
BENCHMARK(BM_Surface)->Args({0, 7, 10, 0})->Args({0, 7, 0, 0})->Args({1, 7, 10, 0})->Args({2, 7, 10, 0})->Unit(benchmark::kMillisecond);
BENCHMARK(BM_Surface)
    ->Args({0, 7, 10, 200000})
    ->Args({0, 7, 10, 50000})
    ->Args({0, 7, 10, 10000})
    ->Unit(benchmark::kMillisecond)
    ->Iterations(1);

void BM_SelfIntersections(benchmark::State& state) {
  const Fixture& f = fixture();
  SurfaceOptions o;
  o.target_faces = state.range(0);
  o.check_self_intersections = false;
  const Surface s = extract_surface(f.v, solid_label_set(f.v, "skin", f.parents), o).surface;
  std::int64_t n = 0;
  for (auto _ : state) n = surface_self_intersections(s);
  state.counters["faces"] = static_cast<double>(s.faces.rows());
  state.counters["pairs"] = static_cast<double>(n);
}
BENCHMARK(BM_SelfIntersections)->Arg(0)->Arg(50000)->Unit(benchmark::kMillisecond)->Iterations(1);

#ifdef ORTHOSIM_HAVE_VTK_PEER
// the phantom's labels as a VTK image: either the labels themselves or the
// 0/1 indicator of a tissue's solid
vtkSmartPointer<vtkImageData> image(bool binary, const std::vector<int>& labels) {
  const Fixture& f = fixture();
  auto im = vtkSmartPointer<vtkImageData>::New();
  im->SetDimensions(f.v.nx, f.v.ny, f.v.nz);
  im->SetSpacing(f.v.spacing_m[0], f.v.spacing_m[1], f.v.spacing_m[2]);
  im->SetOrigin(f.v.origin_m[0], f.v.origin_m[1], f.v.origin_m[2]);
  im->AllocateScalars(VTK_UNSIGNED_CHAR, 1);
  auto* p = static_cast<unsigned char*>(im->GetScalarPointer());
  std::array<unsigned char, 256> lut{};
  for (int l : labels) lut[static_cast<std::size_t>(l)] = 1;
  for (std::size_t i = 0; i < f.v.labels.size(); ++i) p[i] = binary ? lut[f.v.labels[i]] : f.v.labels[i];
  return im;
}

// VTK flying edges at the 0.5 level of a 0/1 image, surface only (no
// normals, gradients or scalars), as both workloads run it.
vtkSmartPointer<vtkFlyingEdges3D> flying_edges(vtkImageData* im) {
  auto fe = vtkSmartPointer<vtkFlyingEdges3D>::New();
  fe->SetInputData(im);
  fe->SetValue(0, 0.5);
  fe->ComputeNormalsOff();
  fe->ComputeGradientsOff();
  fe->ComputeScalarsOff();
  return fe;
}

Surface to_surface(vtkPolyData* pd) {
  Surface s;
  s.vertices.resize(pd->GetNumberOfPoints(), 3);
  for (vtkIdType i = 0; i < pd->GetNumberOfPoints(); ++i) {
    double x[3];
    pd->GetPoint(i, x);
    s.vertices.row(i) << x[0], x[1], x[2];
  }
  s.faces.resize(pd->GetNumberOfPolys(), 3);
  vtkCellArray* polys = pd->GetPolys();
  polys->InitTraversal();
  vtkIdType npts = 0;
  const vtkIdType* pts = nullptr;
  for (Eigen::Index f = 0; polys->GetNextCell(npts, pts); ++f)
    for (int k = 0; k < 3; ++k) s.faces(f, k) = static_cast<std::int32_t>(pts[k]);
  return s;
}

// VTK's SMP back-end here is TBB, so the same tbb::global_control limits
// it (vtkSMPTools.h of VTK 9.1 does not compile as C++20)
auto vtk_threads() { return thread_limit(); }

// skin only: every non-background label. Discrete flying edges on a 0/1
// image extracts the boundary of label 1, the solid.
void BM_VTK_DiscreteFlyingEdges(benchmark::State& state) {
  const auto limit = vtk_threads();
  const Fixture& f = fixture();
  const std::string tissue = kTissues[state.range(0)];
  auto im = image(true, solid_label_set(f.v, tissue, f.parents));
  vtkNew<vtkDiscreteFlyingEdges3D> fe;
  fe->SetInputData(im);
  fe->SetValue(0, 1);
  fe->ComputeNormalsOff();
  fe->ComputeGradientsOff();
  fe->ComputeScalarsOff();
  for (auto _ : state) {
    fe->Modified();
    fe->Update();
  }
  vtkPolyData* out = fe->GetOutput();
  state.SetLabel(tissue);
  state.counters["faces"] = static_cast<double>(out->GetNumberOfPolys());
  error_counters(state, to_surface(out), tissue);
}
BENCHMARK(BM_VTK_DiscreteFlyingEdges)->Arg(0)->Arg(1)->Arg(2)->Unit(benchmark::kMillisecond);

void BM_VTK_FlyingEdges(benchmark::State& state) {
  const auto limit = vtk_threads();
  const Fixture& f = fixture();
  const std::string tissue = kTissues[state.range(0)];
  auto im = image(true, solid_label_set(f.v, tissue, f.parents));
  auto fe = flying_edges(im);
  for (auto _ : state) {
    fe->Modified();
    fe->Update();
  }
  vtkPolyData* out = fe->GetOutput();
  state.SetLabel(tissue);
  state.counters["faces"] = static_cast<double>(out->GetNumberOfPolys());
  error_counters(state, to_surface(out), tissue);
}
BENCHMARK(BM_VTK_FlyingEdges)->Arg(0)->Arg(1)->Arg(2)->Unit(benchmark::kMillisecond);
#endif

// ---- harness rows (orthosim bench; tests/bench/bench_results.h) -------------------------

void results(const std::string& path, bool quick) {
  namespace ob = orthosim::bench;
  if (quick) g_size = 128, g_samples = 4000;
  tbb::global_control limit(tbb::global_control::max_allowed_parallelism, 2);
  ob::Results out("surface", "surface_bench", quick);
  const Fixture& f = fixture();
  const char* size = quick ? "phantom 128^3 (0.6 x 0.6 x 1.0 mm)" : "phantom 256^3 (0.3 x 0.3 x 0.5 mm)";
  auto fill = [&](ob::Row& row, const SurfaceResult& r, const std::string& tissue) {
    const auto [mean, haus] = surface_error(r.surface, tissue);
    row.error("Hausdorff to the analytic interface (voxels)", haus, "<=", 2);
    row.x = static_cast<double>(r.metrics.faces);
    row.extra = {{"tissue", tissue}, {"faces", r.metrics.faces}, {"mean_vox", mean}, {"extract_s", r.metrics.extract_s},
                 {"solid_s", r.metrics.solid_s}, {"smooth_s", r.metrics.smooth_s}, {"decimate_s", r.metrics.decimate_s}};
  };
  for (const char* tissue : kTissues) {
    const std::vector<int> labels = solid_label_set(f.v, tissue, f.parents);
    SurfaceOptions o;
    o.sigma_vox = 0, o.smooth_iterations = 0, o.check_self_intersections = false;
    SurfaceResult r;
    ob::Row row;
    row.workload = std::string(size) + ", binary extraction (no Gaussian, no Taubin) against VTK flying edges";
    row.setting = tissue;
    auto ours = [&] { r = extract_surface(f.v, labels, o); };
#ifdef ORTHOSIM_HAVE_VTK_PEER
    auto im = image(true, labels);
    auto fe = flying_edges(im);
    ob::time_alternating(quick ? 3 : 5, ours, [&] { fe->Modified(); fe->Update(); }, &row.seconds, &row.peer_seconds);
    row.peer = "VTK vtkFlyingEdges3D";
    row.peer_error = surface_error(to_surface(fe->GetOutput()), tissue).second;
    fill(row, r, tissue);
    row.extra["peer_faces"] = fe->GetOutput()->GetNumberOfPolys();
#else
    row.seconds = ob::time_runs(quick ? 3 : 5, ours);
    fill(row, r, tissue);
#endif
    out.add(row);
  }
#ifndef ORTHOSIM_HAVE_VTK_PEER
  out.note("VTK flying-edges peer not built (configure with -DORTHOSIM_WITH_VTK_PEER=ON)");
#endif
  struct Setting {
    const char* name;
    double sigma;
    int taubin;
    std::int64_t faces;
    DecimationCost cost = DecimationCost::lindstrom_turk;
  };
  std::vector<Setting> settings = {{"Gaussian 0.7", 0.7, 0, 0}, {"defaults (Gaussian 0.7, Taubin 10)", 0.7, 10, 0}};
  if (!quick) {
    settings.push_back({"defaults, decimated to 50 000 faces", 0.7, 10, 50000});
    settings.push_back({"defaults, decimated to 50 000 faces, Garland-Heckbert", 0.7, 10, 50000, DecimationCost::garland_heckbert});
  }
  const std::vector<int> labels = solid_label_set(f.v, "skin", f.parents);
  for (const Setting& st : settings) {
    SurfaceOptions o;
    o.sigma_vox = st.sigma, o.smooth_iterations = st.taubin, o.target_faces = st.faces, o.check_self_intersections = false;
    o.decimation = st.cost;
    SurfaceResult r;
    ob::Row row;
    row.workload = std::string(size) + ", skin: time and faces against error by setting";
    row.setting = st.name;
    row.seconds = ob::time_runs(st.faces ? 1 : (quick ? 3 : 5), [&] { r = extract_surface(f.v, labels, o); }, st.faces ? 0 : 1);
    fill(row, r, "skin");
    out.add(row);
  }
  out.write(path);
}

}  // namespace

int main(int argc, char** argv) {
  orthosim::bench::CommonArgs common = orthosim::bench::parse_common(argc, argv);
  if (!common.results.empty()) {
    results(common.results, common.quick);
    return 0;
  }
  int n = static_cast<int>(common.rest.size());
  benchmark::Initialize(&n, common.rest.data());
  if (benchmark::ReportUnrecognizedArguments(n, common.rest.data())) return 1;
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
