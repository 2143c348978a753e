// Box Lx x Ly x Lz [m] with corner at the origin, tetrahedra of target size h [m].
// Parameters are overridable: gmsh -setnumber Lx 0.05 ... or thermognn's loader (defines them first).
DefineConstant[ Lx = 0.04, Ly = 0.04, Lz = 0.02, h = 0.008 ];
SetFactory("OpenCASCADE");
Box(1) = {0, 0, 0, Lx, Ly, Lz};
MeshSize{ PointsOf{ Volume{1}; } } = h;
Mesh.CharacteristicLengthMax = h;
Physical Volume(1) = {1};
