/* libsipmss-expat-compat.so: a preload library for ParaView 5.11 on a libexpat that defers
 * reparsing (expat 2.6, and Debian bookworm's 2.5.0 since its CVE-2023-52425 fix).
 *
 * VTK 9.2's XML parser (vtkXMLParser, used by the .vtp/.vtu readers and by RedistributeDataSet's
 * exchange of pieces) feeds expat in chunks and expects every complete element to be reported
 * by the time its chunk is parsed. With reparse deferral, expat may hold back an element until
 * more input arrives, and the readers lose data: RedistributeDataSet's pieces come back without
 * their cells (VTK issue 19258). Later VTK turns the deferral off for its parsers; this library
 * does the same for every parser the process creates, by wrapping XML_ParserCreate and
 * XML_ParserCreateNS (those VTK calls) when preloaded:
 *
 *   LD_PRELOAD=$SIPMSS_EXPAT_COMPAT pvbatch script.py
 *   mpirun -x LD_PRELOAD=$SIPMSS_EXPAT_COMPAT -np 4 pvbatch script.py
 *
 * The deferral protects against quadratic parse times on hostile XML with huge tokens; without
 * it expat parses as 2.5.0 did before the fix. SIPMSS's filters do not need it. */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <expat.h>

static XML_Parser WithoutDeferral(XML_Parser parser)
{
  if (parser)
  {
    XML_SetReparseDeferralEnabled(parser, XML_FALSE);
  }
  return parser;
}

XML_Parser XML_ParserCreate(const XML_Char* encoding)
{
  static XML_Parser (*next)(const XML_Char*);
  if (!next)
  {
    next = (XML_Parser(*)(const XML_Char*))dlsym(RTLD_NEXT, "XML_ParserCreate");
  }
  return next ? WithoutDeferral(next(encoding)) : NULL;
}

XML_Parser XML_ParserCreateNS(const XML_Char* encoding, XML_Char separator)
{
  static XML_Parser (*next)(const XML_Char*, XML_Char);
  if (!next)
  {
    next = (XML_Parser(*)(const XML_Char*, XML_Char))dlsym(RTLD_NEXT, "XML_ParserCreateNS");
  }
  return next ? WithoutDeferral(next(encoding, separator)) : NULL;
}
