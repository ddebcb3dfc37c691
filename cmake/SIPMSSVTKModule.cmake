# Builds the VTK module SIPMSS::Filters, its Python package `sipmss` and (for the paraview
# frontend) the ParaView plugin.
#
# The module is described by the top-level vtk.module. vtk_module_build() adds the directory that
# holds a module's vtk.module as a subdirectory (same path below the binary dir); for the project
# root that would be the root binary dir itself. So the module is scanned through
# Filters/vtk.module, a symlink to the top-level file: VTK reads the same description, and the
# module's directory (sources, CMakeLists.txt, binary dir) is Filters/. Only public VTK API is used;
# this works with VTK 9.1 and with ParaView 5.11's VTK 9.2.

set(BUILD_SHARED_LIBS ON) # a static module would give a static plugin and no Python extension

if (SIPMSS_FRONTEND STREQUAL "paraview")
  # Ask only for what is used: without components, ParaView's config wants Qt5 development
  # packages and the whole client stack.
  find_package(ParaView 5.10 REQUIRED COMPONENTS RemotingCore RemotingServerManager
    OPTIONAL_COMPONENTS Python)
  set(_sipmss_vtk_components CommonCore CommonDataModel CommonExecutionModel FiltersCore
    FiltersSources IOPLY Python WrappingPythonCore)
  find_package(VTK REQUIRED COMPONENTS ${_sipmss_vtk_components})
  set(SIPMSS_PARAVIEW_VERSION "${ParaView_VERSION}")
else ()
  find_package(VTK 9 REQUIRED COMPONENTS CommonCore CommonDataModel CommonExecutionModel
    FiltersCore FiltersSources IOPLY Python WrappingPythonCore)
endif ()
message(STATUS "SIPMSS: building the VTK module against VTK ${VTK_VERSION} (${VTK_DIR})")

find_package(Python3 REQUIRED COMPONENTS Interpreter Development.Module)

vtk_module_scan(
  MODULE_FILES      "${CMAKE_SOURCE_DIR}/Filters/vtk.module"
  REQUEST_MODULES   SIPMSS::Filters
  PROVIDES_MODULES  _sipmss_modules
  ENABLE_TESTS      OFF) # our filter tests live in Testing/ (plain CTest, see below)

# C++ users: `find_package(SIPMSS)` then link SIPMSS::Filters, from this build tree (add it to
# CMAKE_PREFIX_PATH) or from an installed prefix. vtk_module_build installs the headers, the
# targets and the module properties into CMAKE_DESTINATION and, with INSTALL_HEADERS and
# INSTALL_EXPORT, also export()s the same targets into that directory below the build tree; the
# build tree's lib/cmake/SIPMSS mirrors the install layout, so one SIPMSSConfig.cmake serves both.
set(SIPMSS_CMAKE_DESTINATION "${CMAKE_INSTALL_LIBDIR}/cmake/SIPMSS")
vtk_module_build(
  MODULES              ${_sipmss_modules}
  PACKAGE              SIPMSS
  INSTALL_HEADERS      ON
  HEADERS_DESTINATION  "${CMAKE_INSTALL_INCLUDEDIR}/sipmss"
  CMAKE_DESTINATION    "${SIPMSS_CMAKE_DESTINATION}"
  INSTALL_EXPORT       SIPMSS
  VERSION              "${PROJECT_VERSION}"
  SOVERSION            "1")
# What the consumer's VTK must be: the same major.minor and the same build of it (ParaView's VTK
# names its libraries libvtk*-pv<version>, a plain VTK libvtk*-<version>), told apart by the
# soname of VTK::CommonCore.
get_target_property(_sipmss_vtk_configs VTK::CommonCore IMPORTED_CONFIGURATIONS)
list(GET _sipmss_vtk_configs 0 _sipmss_vtk_config)
get_target_property(SIPMSS_VTK_COMMONCORE_SONAME VTK::CommonCore
  "IMPORTED_SONAME_${_sipmss_vtk_config}")
if (NOT SIPMSS_VTK_COMMONCORE_SONAME)
  set(SIPMSS_VTK_COMMONCORE_SONAME "")
endif ()
if (SIPMSS_FRONTEND STREQUAL "paraview")
  set(SIPMSS_VTK_FLAVOUR "the VTK of ParaView ${ParaView_VERSION}")
else ()
  set(SIPMSS_VTK_FLAVOUR "a plain VTK")
endif ()
vtk_module_export_find_packages(
  CMAKE_DESTINATION    "${SIPMSS_CMAKE_DESTINATION}"
  FILE_NAME            "SIPMSS-vtk-module-find-packages.cmake"
  MODULES              ${_sipmss_modules})
# SIPMSSConfig.cmake finds its VTK, then includes the files above. It locates everything relative
# to itself, so the one file serves the build tree and any (moved) install prefix.
include(CMakePackageConfigHelpers)
set(_sipmss_cmake_build_dir "${CMAKE_BINARY_DIR}/${SIPMSS_CMAKE_DESTINATION}")
configure_package_config_file("${CMAKE_SOURCE_DIR}/cmake/SIPMSSConfig.cmake.in"
  "${_sipmss_cmake_build_dir}/SIPMSSConfig.cmake"
  INSTALL_DESTINATION "${SIPMSS_CMAKE_DESTINATION}"
  NO_SET_AND_CHECK_MACRO)
write_basic_package_version_file("${_sipmss_cmake_build_dir}/SIPMSSConfigVersion.cmake"
  VERSION "${PROJECT_VERSION}"
  COMPATIBILITY SameMinorVersion) # 0.x: a minor release may change the API
install(
  FILES       "${_sipmss_cmake_build_dir}/SIPMSSConfig.cmake"
              "${_sipmss_cmake_build_dir}/SIPMSSConfigVersion.cmake"
  DESTINATION "${SIPMSS_CMAKE_DESTINATION}"
  COMPONENT   development)

# Python: `import sipmss` / `from sipmss import vtkSIPMSSCluster`.
set(SIPMSS_PYTHON_SITE "${CMAKE_INSTALL_LIBDIR}/python3/dist-packages")
vtk_module_wrap_python(
  MODULES              ${_sipmss_modules}
  PYTHON_PACKAGE       "sipmss"
  MODULE_DESTINATION   "${SIPMSS_PYTHON_SITE}"
  LIBRARY_DESTINATION  "${CMAKE_INSTALL_LIBDIR}"
  INSTALL_HEADERS      OFF
  INSTALL_EXPORT       SIPMSSPython
  TARGET               SIPMSS::Python
  BUILD_STATIC         OFF)
configure_file("${CMAKE_SOURCE_DIR}/Wrapping/Python/sipmss/__init__.py"
  "${CMAKE_BINARY_DIR}/${SIPMSS_PYTHON_SITE}/sipmss/__init__.py" COPYONLY)
install(FILES "${CMAKE_SOURCE_DIR}/Wrapping/Python/sipmss/__init__.py"
  DESTINATION "${SIPMSS_PYTHON_SITE}/sipmss")
set(SIPMSS_PYTHONPATH "${CMAKE_BINARY_DIR}/${SIPMSS_PYTHON_SITE}")

if (SIPMSS_FRONTEND STREQUAL "paraview")
  paraview_plugin_scan(
    PLUGIN_FILES      "${CMAKE_SOURCE_DIR}/ParaViewPlugin/paraview.plugin"
    PROVIDES_PLUGINS  _sipmss_plugins
    ENABLE_BY_DEFAULT ON)
  paraview_plugin_build(
    PLUGINS           ${_sipmss_plugins}
    TARGET            SIPMSSPlugins
    LIBRARY_SUBDIRECTORY "paraview-plugins"
    AUTOLOAD          ""
    INSTALL_HEADERS   OFF # SIPMSSPlugins.h serves only static plugins linked into an application
    ADD_INSTALL_RPATHS ON)
  set(SIPMSS_PLUGIN_DIR "${CMAKE_BINARY_DIR}/${CMAKE_INSTALL_LIBDIR}/paraview-plugins/SIPMSS")

  # ParaView 5.11's XML readers (.vtp files, RedistributeDataSet's exchange of pieces) lose data
  # on a libexpat that defers reparsing (2.6; Debian bookworm's 2.5.0 since its CVE-2023-52425
  # fix): a preload library that turns the deferral off (ParaViewPlugin/expat_compat.c). Built
  # when expat has the switch (paraview-dev depends on libexpat1-dev).
  find_package(EXPAT QUIET)
  if (EXPAT_FOUND)
    include(CheckSymbolExists)
    set(CMAKE_REQUIRED_INCLUDES ${EXPAT_INCLUDE_DIRS})
    set(CMAKE_REQUIRED_LIBRARIES ${EXPAT_LIBRARIES})
    check_symbol_exists(XML_SetReparseDeferralEnabled expat.h SIPMSS_EXPAT_REPARSE_DEFERRAL)
    unset(CMAKE_REQUIRED_INCLUDES)
    unset(CMAKE_REQUIRED_LIBRARIES)
  endif ()
  if (SIPMSS_EXPAT_REPARSE_DEFERRAL)
    add_library(sipmss_expat_compat SHARED "${CMAKE_SOURCE_DIR}/ParaViewPlugin/expat_compat.c")
    target_link_libraries(sipmss_expat_compat PRIVATE EXPAT::EXPAT ${CMAKE_DL_LIBS})
    set_target_properties(sipmss_expat_compat PROPERTIES
      OUTPUT_NAME "sipmss-expat-compat"
      LIBRARY_OUTPUT_DIRECTORY "${CMAKE_BINARY_DIR}/${CMAKE_INSTALL_LIBDIR}")
    install(TARGETS sipmss_expat_compat LIBRARY DESTINATION "${CMAKE_INSTALL_LIBDIR}")
    set(SIPMSS_EXPAT_COMPAT "${CMAKE_BINARY_DIR}/${CMAKE_INSTALL_LIBDIR}/libsipmss-expat-compat.so")
  endif ()
endif ()

# The environment tests (and users) need: our Python package and, for an unpacked VTK prefix,
# its libraries and vtkmodules (they are not on the default search paths).
set(SIPMSS_TEST_ENV "PYTHONPATH=path_list_prepend:${SIPMSS_PYTHONPATH}"
  "SIPMSS_SHARED_DATA_DIR=set:${SIPMSS_SHARED_DATA_DIR}")
set(SIPMSS_ENV_SH "export PYTHONPATH=\"${SIPMSS_PYTHONPATH}\${PYTHONPATH:+:\$PYTHONPATH}\"\n")
if (SIPMSS_FRONTEND STREQUAL "vtk")
  get_filename_component(_vtk_prefix "${VTK_DIR}/../../../.." ABSOLUTE)
  if (NOT _vtk_prefix STREQUAL "/usr")
    set(_vtk_libdir "${_vtk_prefix}/lib/${CMAKE_LIBRARY_ARCHITECTURE}")
    set(_vtk_pydir "${_vtk_prefix}/lib/python3/dist-packages")
    list(APPEND SIPMSS_TEST_ENV "LD_LIBRARY_PATH=path_list_prepend:${_vtk_libdir}"
      "PYTHONPATH=path_list_append:${_vtk_pydir}")
    string(APPEND SIPMSS_ENV_SH
      "export LD_LIBRARY_PATH=\"${_vtk_libdir}\${LD_LIBRARY_PATH:+:\$LD_LIBRARY_PATH}\"\n"
      "export PYTHONPATH=\"\$PYTHONPATH:${_vtk_pydir}\"\n")
  endif ()
endif ()
if (SIPMSS_FRONTEND STREQUAL "paraview")
  list(APPEND SIPMSS_TEST_ENV "PV_PLUGIN_PATH=set:${SIPMSS_PLUGIN_DIR}")
  string(APPEND SIPMSS_ENV_SH "export PV_PLUGIN_PATH=\"${SIPMSS_PLUGIN_DIR}\"\n")
  if (SIPMSS_EXPAT_COMPAT)
    # (not preloaded here: `LD_PRELOAD=$SIPMSS_EXPAT_COMPAT pvbatch ...`, README "MPI")
    string(APPEND SIPMSS_ENV_SH "export SIPMSS_EXPAT_COMPAT=\"${SIPMSS_EXPAT_COMPAT}\"\n")
  endif ()
endif ()
# `. build/<preset>/sipmss-env.sh` sets up a shell to use this build from Python or ParaView.
file(WRITE "${CMAKE_BINARY_DIR}/sipmss-env.sh"
  "# Source this file to use this SIPMSS build from Python, pvpython or paraview.\n${SIPMSS_ENV_SH}")

if (BUILD_TESTING)
  add_subdirectory(Testing/Cxx)
  add_subdirectory(Testing/Python)
  add_subdirectory(Testing/Consumer)
  if (SIPMSS_FRONTEND STREQUAL "paraview")
    add_subdirectory(Testing/ParaView)
  endif ()
endif ()
