// Independent NDT scores from PCL's own NormalDistributionsTransform, for tofhil's tests.
//
// Usage: ndt_reference REF.pcd CLOUD.pcd RESOLUTION OUTLIER_RATIO MIN_POINTS OUT_PREFIX
//
// Builds pcl::NormalDistributionsTransform<PointXYZ, PointXYZ> with REF as target, runs
// align() once (so PCL itself sets up d1, d2 from the resolution and outlier ratio), then
// evaluates at the IDENTITY transform with PCL's own computeDerivatives() -- the function
// whose sum divided by the number of points is getTransformationLikelihood(). It also
// evaluates, per point, with PCL's voxel grid and radius search:
//   - the per-point sum of score terms (PCL's score), by calling updateDerivatives(),
//   - the largest term (Autoware pclomp NVTL's nearest-voxel score),
//   - exp(-q^T C^-1 q / 2) of the leaf containing the point (0 if it has < MIN_POINTS).
// Writes OUT_PREFIX_summary.txt (key value lines), OUT_PREFIX_points.txt (one row per
// cloud point: sum nearest has_neighbour cell_likelihood) and OUT_PREFIX_cells.txt (one
// row per searchable leaf: nr_points mean[3] cov[9] after PCL's eigenvalue floor).
// Finally it runs a real align() (PCL defaults) and records getTransformationLikelihood(),
// the final transformation and the cloud PCL transformed (OUT_PREFIX_aligned.pcd).
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include <pcl/io/pcd_io.h>
#include <pcl/point_types.h>
#include <pcl/registration/ndt.h>

using Cloud = pcl::PointCloud<pcl::PointXYZ>;

class NdtProbe : public pcl::NormalDistributionsTransform<pcl::PointXYZ, pcl::PointXYZ> {
public:
  double d1() const { return gauss_d1_; }
  double d2() const { return gauss_d2_; }

  // PCL's score of the input cloud at the identity transform (sum over points).
  double identityScore() {
    Eigen::Matrix<double, 6, 1> grad;
    Eigen::Matrix<double, 6, 6> hess;
    Eigen::Matrix<double, 6, 1> zero = Eigen::Matrix<double, 6, 1>::Zero();
    return computeDerivatives(grad, hess, *input_, zero, false);
  }

  void perPoint(std::FILE* out, double& nvtl, double& mean_cell_lik) {
    Eigen::Matrix<double, 6, 1> grad;
    Eigen::Matrix<double, 6, 6> hess;
    double nearest_sum = 0.0, lik_sum = 0.0;
    std::size_t found = 0;
    const auto& cells = target_cells_;
    const Eigen::Vector3i min_b = cells.getMinBoxCoordinates().head<3>();
    const Eigen::Vector3i max_b = cells.getMaxBoxCoordinates().head<3>();
    const float inv = 1.0f / resolution_;
    for (const auto& pt : *input_) {
      std::vector<TargetGridLeafConstPtr> neighborhood;
      std::vector<float> distances;
      target_cells_.radiusSearch(pt, resolution_, neighborhood, distances);
      double sum = 0.0, nearest = 0.0;
      for (const auto& cell : neighborhood) {
        const Eigen::Vector3d x_trans = pt.getVector3fMap().cast<double>() - cell->getMean();
        grad.setZero();
        hess.setZero();
        const double s = updateDerivatives(grad, hess, x_trans, cell->getInverseCov(), false);
        sum += s;
        if (s > nearest) nearest = s;  // Autoware: max over neighbours, starting at 0
      }
      if (!neighborhood.empty()) { ++found; nearest_sum += nearest; }
      // Leaf containing the point (guard the box: getLeaf() does not).
      double lik = 0.0;
      const Eigen::Vector3i ijk(static_cast<int>(std::floor(pt.x * inv)),
                                static_cast<int>(std::floor(pt.y * inv)),
                                static_cast<int>(std::floor(pt.z * inv)));
      if ((ijk.array() >= min_b.array()).all() && (ijk.array() <= max_b.array()).all()) {
        pcl::PointXYZ q = pt;
        auto leaf = target_cells_.getLeaf(q);
        if (leaf && leaf->getPointCount() >= min_points_) {
          const Eigen::Vector3d d = pt.getVector3fMap().cast<double>() - leaf->getMean();
          lik = std::exp(-0.5 * d.dot(leaf->getInverseCov() * d));
        }
      }
      lik_sum += lik;
      std::fprintf(out, "%.12g %.12g %d %.12g\n", sum, nearest, neighborhood.empty() ? 0 : 1, lik);
    }
    nvtl = found ? nearest_sum / static_cast<double>(found) : 0.0;
    mean_cell_lik = input_->empty() ? 0.0 : lik_sum / static_cast<double>(input_->size());
  }

  void dumpCells(std::FILE* out) {
    for (const auto& c : *target_cells_.getCentroids()) {
      pcl::PointXYZ q = c;
      auto leaf = target_cells_.getLeaf(q);
      const Eigen::Vector3d m = leaf->getMean();
      const Eigen::Matrix3d cv = leaf->getCov();
      std::fprintf(out, "%d %.17g %.17g %.17g", leaf->getPointCount(), m(0), m(1), m(2));
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) std::fprintf(out, " %.17g", cv(i, j));
      std::fprintf(out, "\n");
    }
  }

  std::size_t cellCount() { return target_cells_.getCentroids()->size(); }
  int min_points_ = 6;
};

int main(int argc, char** argv) {
  if (argc != 7) {
    std::fprintf(stderr, "usage: %s REF.pcd CLOUD.pcd RESOLUTION OUTLIER_RATIO MIN_POINTS OUT_PREFIX\n", argv[0]);
    return 2;
  }
  Cloud::Ptr ref(new Cloud), cloud(new Cloud);
  if (pcl::io::loadPCDFile(argv[1], *ref) < 0 || pcl::io::loadPCDFile(argv[2], *cloud) < 0) return 2;
  const float resolution = std::strtof(argv[3], nullptr);
  const double outlier_ratio = std::strtod(argv[4], nullptr);
  const int min_points = std::atoi(argv[5]);
  const std::string prefix = argv[6];

  NdtProbe ndt;
  ndt.min_points_ = min_points;
  ndt.setMinPointPerVoxel(min_points);  // before setInputTarget (PCL's rule)
  ndt.setResolution(resolution);
  ndt.setOulierRatio(outlier_ratio);
  ndt.setInputTarget(ref);
  ndt.setInputSource(cloud);
  ndt.setMaximumIterations(1);
  Cloud aligned;
  ndt.align(aligned, Eigen::Matrix4f::Identity());  // sets d1, d2 the way PCL does

  const double score = ndt.identityScore();
  std::FILE* fp = std::fopen((prefix + "_points.txt").c_str(), "w");
  double nvtl = 0.0, mean_lik = 0.0;
  ndt.perPoint(fp, nvtl, mean_lik);
  std::fclose(fp);
  std::FILE* fc = std::fopen((prefix + "_cells.txt").c_str(), "w");
  ndt.dumpCells(fc);
  std::fclose(fc);
  std::FILE* fs = std::fopen((prefix + "_summary.txt").c_str(), "w");
  std::fprintf(fs, "pcl_version %s\n", PCL_VERSION_PRETTY);
  std::fprintf(fs, "resolution %.9g\noutlier_ratio %.17g\nmin_points %d\n", resolution, outlier_ratio, min_points);
  std::fprintf(fs, "n_ref %zu\nn_points %zu\n", ref->size(), cloud->size());
  std::fprintf(fs, "cells %zu\n", ndt.cellCount());
  std::fprintf(fs, "d1 %.17g\nd2 %.17g\n", ndt.d1(), ndt.d2());
  std::fprintf(fs, "score_per_point %.17g\n", score / static_cast<double>(cloud->size()));
  std::fprintf(fs, "nvtl %.17g\n", nvtl);
  std::fprintf(fs, "mean_likelihood %.17g\n", mean_lik);

  // A real registration (35 iterations max, step 0.1, epsilon 1e-8 m^2) from the
  // identity: PCL's getTransformationLikelihood() then refers to the cloud PCL itself
  // transformed (the aligned output), which is saved as exact float32 binary PCD.
  NdtProbe reg;
  reg.setMinPointPerVoxel(min_points);
  reg.setResolution(resolution);
  reg.setOulierRatio(outlier_ratio);
  reg.setInputTarget(ref);
  reg.setInputSource(cloud);
  reg.setTransformationEpsilon(1e-8);
  reg.setMaximumIterations(35);
  Cloud out;
  reg.align(out, Eigen::Matrix4f::Identity());
  pcl::io::savePCDFileBinary(prefix + "_aligned.pcd", out);
  std::fprintf(fs, "aligned_iterations %d\n", reg.getFinalNumIteration());
  std::fprintf(fs, "aligned_likelihood %.17g\n", reg.getTransformationLikelihood());
  const Eigen::Matrix4f T = reg.getFinalTransformation();
  std::fprintf(fs, "aligned_transformation");
  for (int i = 0; i < 4; ++i)
    for (int j = 0; j < 4; ++j) std::fprintf(fs, " %.9g", T(i, j));
  std::fprintf(fs, "\n");
  std::fclose(fs);
  return 0;
}
