"""Eclipse Tahu's Sparkplug B payload (``sparkplug_b.proto``), built at run time.

The protobuf schema is Eclipse Tahu's ``sparkplug_b/sparkplug_b.proto`` (proto2, package
``org.eclipse.tahu.protobuf``; Copyright (c) 2015, 2018 Cirrus Link Solutions and others,
EPL-2.0), shipped beside this module unchanged (see README.md: source, commit, licence).
:data:`FILE_DESCRIPTOR` is that file compiled by ``protoc`` (a serialised
``FileDescriptorProto``: ``protoc --descriptor_set_out``, file 0); the message classes are
made from it with protobuf's runtime API (``DescriptorPool.AddSerializedFile`` and
``message_factory.GetMessageClass``, protobuf >= 4.22) in a pool of their own, so no generated
``*_pb2.py`` is checked in: generated code is bound to the protoc version that wrote it
(``ValidateProtobufRuntimeVersion`` refuses an older runtime), the descriptor is not; and a
process that also loads another copy of Tahu's ``sparkplug_b_pb2`` (into protobuf's default
pool) gets no duplicate-file error. ``tests/test_sparkplug.py`` checks these bytes against the
shipped ``.proto`` (every message, field name, number and label).
"""

from __future__ import annotations

import functools
from typing import Any

__all__ = ["DATATYPE", "FILE_DESCRIPTOR", "payload_class"]

#: ``sparkplug_b.proto`` compiled (``FileDescriptorProto``, serialised; protoc 35.1 from
#: grpcio-tools 1.85.1).
FILE_DESCRIPTOR = (
    b'\n\x11sparkplug_b.proto\x12\x19org.eclipse.tahu.protobuf"\x87\x1c\n\x07Paylo'
    b'ad\x12\x1c\n\ttimestamp\x18\x01 \x01(\x04R\ttimestamp\x12C\n\x07metrics\x18\x02 \x03(\x0b2).org.'
    b'eclipse.tahu.protobuf.Payload.MetricR\x07metrics\x12\x10\n\x03seq\x18\x03 \x01'
    b'(\x04R\x03seq\x12\x12\n\x04uuid\x18\x04 \x01(\tR\x04uuid\x12\x12\n\x04body\x18\x05 \x01(\x0cR\x04body\x1a\xc4\x05\n\x08Temp'
    b'late\x12\x18\n\x07version\x18\x01 \x01(\tR\x07version\x12C\n\x07metrics\x18\x02 \x03(\x0b2).org.ec'
    b'lipse.tahu.protobuf.Payload.MetricR\x07metrics\x12U\n\nparameter'
    b's\x18\x03 \x03(\x0b25.org.eclipse.tahu.protobuf.Payload.Template.Par'
    b'ameterR\nparameters\x12!\n\x0ctemplate_ref\x18\x04 \x01(\tR\x0btemplateRef\x12#\n'
    b'\ris_definition\x18\x05 \x01(\x08R\x0cisDefinition\x1a\xaf\x03\n\tParameter\x12\x12\n\x04name'
    b'\x18\x01 \x01(\tR\x04name\x12\x12\n\x04type\x18\x02 \x01(\rR\x04type\x12\x1d\n\tint_value\x18\x03 \x01(\rH\x00R\x08i'
    b'ntValue\x12\x1f\n\nlong_value\x18\x04 \x01(\x04H\x00R\tlongValue\x12!\n\x0bfloat_value\x18'
    b'\x05 \x01(\x02H\x00R\nfloatValue\x12#\n\x0cdouble_value\x18\x06 \x01(\x01H\x00R\x0bdoubleValue'
    b'\x12%\n\rboolean_value\x18\x07 \x01(\x08H\x00R\x0cbooleanValue\x12#\n\x0cstring_value\x18'
    b'\x08 \x01(\tH\x00R\x0bstringValue\x12x\n\x0fextension_value\x18\t \x01(\x0b2M.org.ecli'
    b'pse.tahu.protobuf.Payload.Template.Parameter.ParameterVa'
    b'lueExtensionH\x00R\x0eextensionValue\x1a#\n\x17ParameterValueExtensio'
    b'n*\x08\x08\x01\x10\x80\x80\x80\x80\x02B\x07\n\x05value*\x08\x08\x06\x10\x80\x80\x80\x80\x02\x1a\x9e\x05\n\x07DataSet\x12$\n\x0enum_of_col'
    b'umns\x18\x01 \x01(\x04R\x0cnumOfColumns\x12\x18\n\x07columns\x18\x02 \x03(\tR\x07columns\x12\x14\n\x05ty'
    b'pes\x18\x03 \x03(\rR\x05types\x12B\n\x04rows\x18\x04 \x03(\x0b2..org.eclipse.tahu.protob'
    b'uf.Payload.DataSet.RowR\x04rows\x1a\x88\x03\n\x0cDataSetValue\x12\x1d\n\tint_val'
    b'ue\x18\x01 \x01(\rH\x00R\x08intValue\x12\x1f\n\nlong_value\x18\x02 \x01(\x04H\x00R\tlongValue\x12!\n'
    b'\x0bfloat_value\x18\x03 \x01(\x02H\x00R\nfloatValue\x12#\n\x0cdouble_value\x18\x04 \x01(\x01H\x00'
    b'R\x0bdoubleValue\x12%\n\rboolean_value\x18\x05 \x01(\x08H\x00R\x0cbooleanValue\x12#\n\x0c'
    b'string_value\x18\x06 \x01(\tH\x00R\x0bstringValue\x12x\n\x0fextension_value\x18\x07 \x01'
    b'(\x0b2M.org.eclipse.tahu.protobuf.Payload.DataSet.DataSetVa'
    b'lue.DataSetValueExtensionH\x00R\x0eextensionValue\x1a!\n\x15DataSetVa'
    b'lueExtension*\x08\x08\x01\x10\x80\x80\x80\x80\x02B\x07\n\x05value\x1ad\n\x03Row\x12S\n\x08elements\x18\x01 \x03(\x0b'
    b'27.org.eclipse.tahu.protobuf.Payload.DataSet.DataSetValu'
    b'eR\x08elements*\x08\x08\x02\x10\x80\x80\x80\x80\x02*\x08\x08\x05\x10\x80\x80\x80\x80\x02\x1a\xf5\x04\n\rPropertyValue\x12\x12\n\x04typ'
    b'e\x18\x01 \x01(\rR\x04type\x12\x17\n\x07is_null\x18\x02 \x01(\x08R\x06isNull\x12\x1d\n\tint_value\x18\x03 \x01('
    b'\rH\x00R\x08intValue\x12\x1f\n\nlong_value\x18\x04 \x01(\x04H\x00R\tlongValue\x12!\n\x0bfloat_'
    b'value\x18\x05 \x01(\x02H\x00R\nfloatValue\x12#\n\x0cdouble_value\x18\x06 \x01(\x01H\x00R\x0bdoubl'
    b'eValue\x12%\n\rboolean_value\x18\x07 \x01(\x08H\x00R\x0cbooleanValue\x12#\n\x0cstring_'
    b'value\x18\x08 \x01(\tH\x00R\x0bstringValue\x12]\n\x11propertyset_value\x18\t \x01(\x0b2..'
    b'org.eclipse.tahu.protobuf.Payload.PropertySetH\x00R\x10propert'
    b'ysetValue\x12c\n\x12propertysets_value\x18\n \x01(\x0b22.org.eclipse.tahu'
    b'.protobuf.Payload.PropertySetListH\x00R\x11propertysetsValue\x12r'
    b'\n\x0fextension_value\x18\x0b \x01(\x0b2G.org.eclipse.tahu.protobuf.Payl'
    b'oad.PropertyValue.PropertyValueExtensionH\x00R\x0eextensionVal'
    b'ue\x1a"\n\x16PropertyValueExtension*\x08\x08\x01\x10\x80\x80\x80\x80\x02B\x07\n\x05value\x1au\n\x0bPrope'
    b'rtySet\x12\x12\n\x04keys\x18\x01 \x03(\tR\x04keys\x12H\n\x06values\x18\x02 \x03(\x0b20.org.eclipse'
    b'.tahu.protobuf.Payload.PropertyValueR\x06values*\x08\x08\x03\x10\x80\x80\x80\x80\x02\x1am'
    b'\n\x0fPropertySetList\x12P\n\x0bpropertyset\x18\x01 \x03(\x0b2..org.eclipse.tah'
    b'u.protobuf.Payload.PropertySetR\x0bpropertyset*\x08\x08\x02\x10\x80\x80\x80\x80\x02\x1a\xef\x01'
    b'\n\x08MetaData\x12"\n\ris_multi_part\x18\x01 \x01(\x08R\x0bisMultiPart\x12!\n\x0cconten'
    b't_type\x18\x02 \x01(\tR\x0bcontentType\x12\x12\n\x04size\x18\x03 \x01(\x04R\x04size\x12\x10\n\x03seq\x18\x04 \x01'
    b'(\x04R\x03seq\x12\x1b\n\tfile_name\x18\x05 \x01(\tR\x08fileName\x12\x1b\n\tfile_type\x18\x06 \x01(\tR'
    b'\x08fileType\x12\x10\n\x03md5\x18\x07 \x01(\tR\x03md5\x12 \n\x0bdescription\x18\x08 \x01(\tR\x0bdescri'
    b'ption*\x08\x08\t\x10\x80\x80\x80\x80\x02\x1a\x9c\x07\n\x06Metric\x12\x12\n\x04name\x18\x01 \x01(\tR\x04name\x12\x14\n\x05alias\x18'
    b'\x02 \x01(\x04R\x05alias\x12\x1c\n\ttimestamp\x18\x03 \x01(\x04R\ttimestamp\x12\x1a\n\x08datatype\x18\x04'
    b' \x01(\rR\x08datatype\x12#\n\ris_historical\x18\x05 \x01(\x08R\x0cisHistorical\x12!\n\x0ci'
    b's_transient\x18\x06 \x01(\x08R\x0bisTransient\x12\x17\n\x07is_null\x18\x07 \x01(\x08R\x06isNull\x12'
    b'G\n\x08metadata\x18\x08 \x01(\x0b2+.org.eclipse.tahu.protobuf.Payload.Me'
    b'taDataR\x08metadata\x12N\n\nproperties\x18\t \x01(\x0b2..org.eclipse.tahu.'
    b'protobuf.Payload.PropertySetR\nproperties\x12\x1d\n\tint_value\x18\n '
    b'\x01(\rH\x00R\x08intValue\x12\x1f\n\nlong_value\x18\x0b \x01(\x04H\x00R\tlongValue\x12!\n\x0bfloa'
    b't_value\x18\x0c \x01(\x02H\x00R\nfloatValue\x12#\n\x0cdouble_value\x18\r \x01(\x01H\x00R\x0bdou'
    b'bleValue\x12%\n\rboolean_value\x18\x0e \x01(\x08H\x00R\x0cbooleanValue\x12#\n\x0cstrin'
    b'g_value\x18\x0f \x01(\tH\x00R\x0bstringValue\x12!\n\x0bbytes_value\x18\x10 \x01(\x0cH\x00R\nbyt'
    b'esValue\x12Q\n\rdataset_value\x18\x11 \x01(\x0b2*.org.eclipse.tahu.protob'
    b'uf.Payload.DataSetH\x00R\x0cdatasetValue\x12T\n\x0etemplate_value\x18\x12 \x01'
    b'(\x0b2+.org.eclipse.tahu.protobuf.Payload.TemplateH\x00R\rtempl'
    b'ateValue\x12i\n\x0fextension_value\x18\x13 \x01(\x0b2>.org.eclipse.tahu.pro'
    b'tobuf.Payload.Metric.MetricValueExtensionH\x00R\x0eextensionVa'
    b'lue\x1a \n\x14MetricValueExtension*\x08\x08\x01\x10\x80\x80\x80\x80\x02B\x07\n\x05value*\x08\x08\x06\x10\x80\x80\x80\x80\x02'
    b'*\xf2\x03\n\x08DataType\x12\x0b\n\x07Unknown\x10\x00\x12\x08\n\x04Int8\x10\x01\x12\t\n\x05Int16\x10\x02\x12\t\n\x05Int32'
    b'\x10\x03\x12\t\n\x05Int64\x10\x04\x12\t\n\x05UInt8\x10\x05\x12\n\n\x06UInt16\x10\x06\x12\n\n\x06UInt32\x10\x07\x12\n\n\x06UInt'
    b'64\x10\x08\x12\t\n\x05Float\x10\t\x12\n\n\x06Double\x10\n\x12\x0b\n\x07Boolean\x10\x0b\x12\n\n\x06String\x10\x0c\x12\x0c\n\x08'
    b'DateTime\x10\r\x12\x08\n\x04Text\x10\x0e\x12\x08\n\x04UUID\x10\x0f\x12\x0b\n\x07DataSet\x10\x10\x12\t\n\x05Bytes\x10\x11\x12\x08'
    b'\n\x04File\x10\x12\x12\x0c\n\x08Template\x10\x13\x12\x0f\n\x0bPropertySet\x10\x14\x12\x13\n\x0fPropertySetLi'
    b'st\x10\x15\x12\r\n\tInt8Array\x10\x16\x12\x0e\n\nInt16Array\x10\x17\x12\x0e\n\nInt32Array\x10\x18\x12\x0e\n\nI'
    b'nt64Array\x10\x19\x12\x0e\n\nUInt8Array\x10\x1a\x12\x0f\n\x0bUInt16Array\x10\x1b\x12\x0f\n\x0bUInt32Ar'
    b'ray\x10\x1c\x12\x0f\n\x0bUInt64Array\x10\x1d\x12\x0e\n\nFloatArray\x10\x1e\x12\x0f\n\x0bDoubleArray\x10\x1f\x12'
    b'\x10\n\x0cBooleanArray\x10 \x12\x0f\n\x0bStringArray\x10!\x12\x11\n\rDateTimeArray\x10"B,\n'
    b'\x19org.eclipse.tahu.protobufB\x0fSparkplugBProto'
)

#: ``DataType``: the Sparkplug B data types this output uses (name -> the enum's number).
DATATYPE = {"Int32": 3, "Int64": 4, "UInt64": 8, "Double": 10, "Boolean": 11, "String": 12,
            "DateTime": 13}


@functools.cache
def payload_class() -> Any:
    """``org.eclipse.tahu.protobuf.Payload``: the message class (built once per process).

    Returns:
        The protobuf message class (``Payload()``, ``Payload.FromString(b)``); typed ``Any``:
        its fields exist only at run time.
    """
    from google.protobuf import descriptor_pool, message_factory

    pool = descriptor_pool.DescriptorPool()
    pool.AddSerializedFile(FILE_DESCRIPTOR)
    return message_factory.GetMessageClass(
        pool.FindMessageTypeByName("org.eclipse.tahu.protobuf.Payload"))
